"""Structure of the modelled species against independent truths: the paper's LAIs, the leaf-area
allometry of the parameter file, the LADs (KS on the scenes' own leaf normals), the G-function
(nadir gap fraction), heights, and the effects."""

import math

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from waveforest.effects import UNDERSTORY_HEIGHT_M
from waveforest.vegetation import build, build_scene, lad_by_name, leaf_area_index, nadir_gap_fraction
from waveforest.vegetation.leaves import load_outline
from waveforest.vegetation.params import RES, species_params

PLOT_M2 = 36.0
LAI_PAPER = {"raspberry": 3.35, "fireweed": 2.0}  # docs/method.md §(g) (Kuusk et al. 2004)
REALISED_TOL = 0.02  # the issue: realised LAI / leaf area within 2 % of the target
KS_ALPHA = 0.01
OMEGA_RANGE = (0.75, 1.0)
"""Nadir clumping index ln P / (-G(0) L) accepted as consistent with the LAI and the LAD: random
shoot positions give a Boolean canopy of shoots, whose own leaves hide each other a little
(Omega < 1); Omega < 0.75 would mean stacked leaves (a shoot artefact)."""


def _structure(slug: str, param: str) -> float:
    st = pd.read_csv(RES / "structure.csv", comment="#")
    return float(st[(st.slug == slug) & (st.param == param)]["value"].item())


def _leaf_inclinations(scene, n_tri_per_leaf: int) -> np.ndarray:
    """One inclination (rad) per leaf, from its first triangle's normal."""
    nrm = scene.normals[scene.kind == 1][::n_tri_per_leaf]
    return np.arccos(np.clip(np.abs(nrm[:, 2]), 0, 1))


@pytest.mark.parametrize("slug", ["raspberry", "fireweed"])
@pytest.mark.parametrize("h", [0.6, 1.5])
def test_plot_lai_equals_the_papers(slug, h):
    s = build_scene(slug, h, 3, lai_jitter=0.0)
    assert leaf_area_index(s) == pytest.approx(LAI_PAPER[slug], rel=REALISED_TOL)
    assert leaf_area_index(s) == pytest.approx(LAI_PAPER[slug], rel=1e-5)  # in fact exact


def test_lai_jitter_is_a_uniform_relative_variation_per_instance():
    factors, lais = [], []
    for seed in range(30):
        b = build("fireweed", 1.0, seed)  # default +-10 %
        factors.append(b.jitter_factor)
        lais.append(leaf_area_index(b.scene))
    factors, lais = np.array(factors), np.array(lais)
    assert np.all((factors >= 0.9) & (factors <= 1.1))
    assert factors.min() < 0.95 and factors.max() > 1.05
    np.testing.assert_allclose(lais, LAI_PAPER["fireweed"] * factors, rtol=REALISED_TOL)


def _young_birch_leaf_area(h: float) -> float:
    """The published chain written out from the papers: Naslund d(h) (Finnish NFI broadleaf
    a = 0.898, b = 0.242), stump diameter 2 + 1.25 d (Laasasenaho 1975), leaf mass
    0.00371 d_s[mm]^1.11993 kg (Johansson 1999 via Majasalmi et al. 2013 Eq. 8), SLA 13.55."""
    s = np.sqrt(h - 1.3)
    d = 0.898 * s / (1 - 0.242 * s)
    return 13.55 * 0.00371 * (10 * (2 + 1.25 * d)) ** 1.11993


@pytest.mark.parametrize("h,area", [(2.5, 2.845), (3.0, 3.251), (5.0, 4.965)])
def test_birch_total_leaf_area_follows_the_published_allometry(h, area):
    assert _young_birch_leaf_area(h) == pytest.approx(area, abs=5e-4)  # the chain's own values
    s = build_scene("birch", h, 4, lai_jitter=0.0)
    assert s.areas[s.kind == 1].sum() == pytest.approx(_young_birch_leaf_area(h), rel=REALISED_TOL)


def test_leaf_area_scale_scales_every_leaf_and_keeps_the_structure():
    base = build_scene("birch", 3.0, 9, lai_jitter=0.0)
    for k in (0.5, 1.5):
        s = build_scene("birch", 3.0, 9, lai_jitter=0.0, leaf_area_scale=k)
        assert (s.kind == 1).sum() == (base.kind == 1).sum()
        np.testing.assert_allclose(s.areas[s.kind == 1], k * base.areas[base.kind == 1], rtol=1e-3)
        np.testing.assert_array_equal(s.triangles[s.kind == 2], base.triangles[base.kind == 2])
    r = build_scene("raspberry", 1.0, 2, lai_jitter=0.0, leaf_area_scale=1.5)
    assert leaf_area_index(r) == pytest.approx(1.5 * 3.35, rel=1e-5)


@pytest.mark.parametrize("slug,h,lad,per_leaf", [("birch", 4.0, "spherical", "birch"),
                                                 ("raspberry", 1.2, "planophile", "raspberry_leaflet"),
                                                 ("fireweed", 1.5, "planophile", "fireweed")])
def test_scene_leaf_normals_follow_the_papers_lad(slug, h, lad, per_leaf):
    s = build_scene(slug, h, 21, lai_jitter=0.0)
    theta = _leaf_inclinations(s, load_outline(per_leaf).n_triangles)[:10_000]
    assert theta.size >= 1000
    assert stats.kstest(theta, lad_by_name(lad).cdf).pvalue > KS_ALPHA
    # and the planophile canopy is not spherical (the check has power)
    other = "spherical" if lad == "planophile" else "planophile"
    assert stats.kstest(theta, lad_by_name(other).cdf).pvalue < 1e-6


@pytest.mark.parametrize("shift", [-15.0, 15.0])
def test_lad_shift_moves_the_mean_leaf_angle_of_the_scene(shift):
    s = build_scene("raspberry", 1.0, 8, lai_jitter=0.0, lad_shift=shift)
    theta = np.degrees(_leaf_inclinations(s, load_outline("raspberry_leaflet").n_triangles))
    target = lad_by_name("planophile").mean_deg + shift
    assert abs(theta.mean() - target) < 4 * theta.std() / math.sqrt(theta.size)


@pytest.mark.parametrize("mean", [30.0, 57.3, 75.0])
def test_mean_leaf_angle_sets_the_birch_mean_inclination(mean):
    s = build_scene("birch", 3.0, 2, lai_jitter=0.0, mean_leaf_angle=mean)
    theta = np.degrees(_leaf_inclinations(s, load_outline("birch").n_triangles))
    assert abs(theta.mean() - mean) < 4 * theta.std() / math.sqrt(theta.size)


def test_all_leaves_horizontal_at_mean_angle_zero():
    s = build_scene("birch", 3.0, 2, mean_leaf_angle=0.0)
    np.testing.assert_allclose(np.abs(s.normals[s.kind == 1][:, 2]), 1.0, atol=1e-4)


def test_leaf_albedo_and_leaf_optics_overrides():
    s = build_scene("birch", 3.0, 1, leaf_albedo=0.8)
    assert np.allclose(s.rho[s.kind == 1], 0.47 * 0.8) and np.allclose(s.tau[s.kind == 1], 0.50 * 0.8)
    assert np.allclose(s.rho[s.kind == 2], 0.50)  # wood unchanged
    s = build_scene("birch", 3.0, 1, leaf_albedo=1.2)  # 0.564 + 0.6 > 1: tau lowered to 1 - rho
    assert np.allclose(s.rho[s.kind == 1], 0.47 * 1.2)
    assert np.allclose(s.rho[s.kind == 1] + s.tau[s.kind == 1], 1.0)
    s = build_scene("birch", 3.0, 1, leaf_rho=0.35, leaf_tau=0.45)
    assert np.allclose(s.rho[s.kind == 1], 0.35) and np.allclose(s.tau[s.kind == 1], 0.45)


def test_understory_fills_the_birch_crown_base_gap_without_changing_the_tree():
    plain = build_scene("birch", 3.0, 6)
    b = build("birch", 3.0, 6, understory=1.5)
    s = b.scene
    n_tree = (plain.kind != 0).sum()
    np.testing.assert_array_equal(s.triangles[:n_tree], plain.triangles[:n_tree])
    low = (s.kind == 1) & (s.triangles[:, :, 2].max(axis=1) <= UNDERSTORY_HEIGHT_M + 1e-4)
    assert s.areas[low].sum() == pytest.approx(1.5 * PLOT_M2, rel=REALISED_TOL)
    assert b.understory_leaf_area_m2 == pytest.approx(1.5 * PLOT_M2, rel=1e-6)
    # the paper's birch has an empty gap between crown base and ground: above the understory
    leaf_z = plain.triangles[plain.kind == 1][:, :, 2]
    crown_base = species_params("birch").structure["crown_base_frac"] * 3.0
    assert leaf_z.min() > crown_base - 0.1 > UNDERSTORY_HEIGHT_M
    # no-op for low vegetation
    r0, r1 = build_scene("raspberry", 1.0, 6), build_scene("raspberry", 1.0, 6, understory=1.5)
    np.testing.assert_array_equal(r0.triangles, r1.triangles)


def test_understory_layers_of_one_seed_are_nested_in_their_lai():
    """A higher understory LAI adds tufts to the same layer (common random numbers for the
    diagnosis's fit): every blade of the LAI-1 layer, base and tip (points that the width
    scaling to the exact LAI leaves in place), is a blade of the LAI-2 layer, in the same order."""
    n_tree = (build_scene("birch", 3.0, 6).kind != 0).sum()
    per_blade = load_outline("blade").n_triangles

    def blades(lai):
        s = build_scene("birch", 3.0, 6, understory=lai)
        tri = s.triangles[n_tree:][s.kind[n_tree:] == 1].reshape(-1, per_blade, 3, 3)
        return tri[:, 0, :2].mean(axis=1), tri[:, 1, 2]  # base (outline x = 0), tip (outline (1, 0))

    (base1, tip1), (base2, tip2) = blades(1.0), blades(2.0)
    assert 1.8 < len(base2) / len(base1) < 2.2
    np.testing.assert_allclose(base2[: len(base1)], base1, atol=1e-5)
    np.testing.assert_allclose(tip2[: len(tip1)], tip1, atol=1e-5)


@pytest.mark.parametrize("seed", [12, 13])
def test_clumping_keeps_the_lai_and_opens_gaps(seed):
    def gap(s):
        return nadir_gap_fraction(s, cell_m=0.02)

    uni = build_scene("raspberry", 1.2, seed, lai_jitter=0.0)
    tight = build_scene("raspberry", 1.2, seed, lai_jitter=0.0, clumping=0.15)
    loose = build_scene("raspberry", 1.2, seed, lai_jitter=0.0, clumping=0.3)
    assert leaf_area_index(tight) == pytest.approx(leaf_area_index(uni), rel=1e-6)
    # the same leaf area in clusters leaves more ground visible, the more so the tighter the
    # clusters (Thomas process: clusters wider than the parent spacing merge into uniformity)
    assert gap(tight) > gap(loose) > gap(uni) + 0.01


@pytest.mark.parametrize("slug", ["raspberry", "fireweed"])
@pytest.mark.parametrize("h", [0.6, 1.8])
def test_nadir_gap_fraction_is_consistent_with_lai_and_g_function(slug, h):
    s = build_scene(slug, h, 30, lai_jitter=0.0)
    lai = leaf_area_index(s)
    g0 = 8 / (3 * math.pi)  # planophile G(0), analytic
    p_leaves = nadir_gap_fraction(s, kinds=(1,), cell_m=0.01)
    omega = math.log(p_leaves) / (-g0 * lai)
    assert OMEGA_RANGE[0] <= omega <= OMEGA_RANGE[1], f"clumping index {omega:.3f}"


@pytest.mark.parametrize("slug,h,outline", [("birch", 2.5, "birch"), ("birch", 5.0, "birch"),
                                            ("raspberry", 0.5, "raspberry_leaflet"),
                                            ("raspberry", 1.8, "raspberry_leaflet"),
                                            ("fireweed", 0.6, "fireweed"), ("fireweed", 2.5, "fireweed")])
def test_scene_top_equals_the_field_height_within_a_leaf(slug, h, outline):
    s = build_scene(slug, h, 13)
    top = float(s.bounds[1, 2])
    leaves = s.triangles[s.kind == 1].reshape(-1, load_outline(outline).n_triangles * 3, 3)
    extent = np.linalg.norm(leaves.max(axis=1) - leaves.min(axis=1), axis=1).max()  # largest leaf
    petiole = _structure(slug, "petiole_m")
    assert h - 0.01 <= top <= h + extent + petiole


def test_surface_relief_has_the_parameter_rms():
    s = build_scene("mineral_soil", 0.0, 3)
    z = s.triangles[:, :, 2].ravel()
    assert z.std() == pytest.approx(_structure("mineral_soil", "relief_rms_m"), rel=0.05)
    assert abs(z.mean()) < 0.01
    assert np.all(s.kind == 0) and np.allclose(s.rho, 0.25)
