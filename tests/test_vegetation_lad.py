"""Leaf angle distributions: analytic densities, exact sampling (KS at n = 10,000), G-function."""

import math

import numpy as np
import pytest
from reference_vegetation import invert_dewit_bisection
from scipy import integrate, stats

from waveforest.vegetation.lad import (
    DEWIT,
    LAD_NAMES,
    LeafAngleDistribution,
    invert_dewit_cdf,
    lad_by_name,
    sample_normals,
)

N_KS = 10_000
KS_ALPHA = 0.01
"""A correct sampler fails a KS test at this level with probability 1 %; the seeds are fixed."""

# mean leaf inclination (deg) of the de Wit types: integral of theta f(theta)
MEAN_DEG = {
    "planophile": math.degrees(math.pi / 4 - 1 / math.pi),
    "erectophile": math.degrees(math.pi / 4 + 1 / math.pi),
    "plagiophile": 45.0,
    "extremophile": 45.0,
    "uniform": 45.0,
    "spherical": math.degrees(1.0),
}
# G(0) = E[cos theta]: (2/pi)(1 + 1/3), (2/pi)(1 - 1/3), (2/pi)(1 + 1/15), (2/pi)(1 - 1/15), 2/pi, 1/2
G_NADIR = {
    "planophile": 8 / (3 * math.pi),
    "erectophile": 4 / (3 * math.pi),
    "plagiophile": 32 / (15 * math.pi),
    "extremophile": 28 / (15 * math.pi),
    "uniform": 2 / math.pi,
    "spherical": 0.5,
}
# beta parameters (mu, nu) of the de Wit types tabulated by Wang et al. (2007)
WANG_2007 = {
    "planophile": (2.770, 1.172),
    "erectophile": (1.172, 2.770),
    "plagiophile": (3.326, 3.326),
    "extremophile": (0.433, 0.433),
    "uniform": (1.0, 1.0),
    "spherical": (1.101, 1.930),
}


@pytest.mark.parametrize("name", LAD_NAMES)
def test_density_integrates_to_one_and_cdf_is_its_integral(name):
    lad = lad_by_name(name)
    assert integrate.quad(lad.pdf, 0, math.pi / 2)[0] == pytest.approx(1.0, abs=1e-10)
    for th in (0.2, 0.7, 1.3):
        assert lad.cdf(th) == pytest.approx(integrate.quad(lad.pdf, 0, th)[0], abs=1e-10)
    assert lad.cdf(0.0) == 0.0 and lad.cdf(math.pi / 2) == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize("name", LAD_NAMES)
def test_mean_angle_and_nadir_g_are_analytic(name):
    lad = lad_by_name(name)
    assert lad.mean_deg == pytest.approx(MEAN_DEG[name], abs=1e-8)
    assert lad.g(0.0) == pytest.approx(G_NADIR[name], abs=1e-9)


@pytest.mark.parametrize("name", LAD_NAMES)
def test_g_function_averages_one_half_over_the_hemisphere(name):
    # any LAD: int_0^{pi/2} G(theta) sin(theta) d theta = 1/2 (Ross 1981)
    lad = lad_by_name(name)
    val = integrate.quad(lambda t: lad.g(t) * math.sin(t), 0, math.pi / 2, limit=100)[0]
    assert val == pytest.approx(0.5, abs=1e-7)


def test_spherical_g_is_one_half_at_every_view_angle_and_vertical_leaves_give_2_over_pi_sin():
    sph = lad_by_name("spherical")
    for v in np.radians([0, 15, 30, 57.5, 75, 90]):
        assert sph.g(v) == pytest.approx(0.5, abs=1e-9)
    vertical = LeafAngleDistribution("fixed", mu=math.pi / 2)
    for v in np.radians([0, 20, 60, 90]):
        assert vertical.g(v) == pytest.approx(2 / math.pi * math.sin(v), abs=1e-12)
    horizontal = LeafAngleDistribution("fixed", mu=0.0)
    assert horizontal.g(math.radians(40)) == pytest.approx(math.cos(math.radians(40)))


@pytest.mark.parametrize("name", LAD_NAMES)
def test_sampled_inclinations_pass_ks_against_the_theoretical_cdf(name):
    lad = lad_by_name(name)
    theta = lad.sample(N_KS, np.random.default_rng(2014))
    assert theta.min() >= 0 and theta.max() <= math.pi / 2
    assert stats.kstest(theta, lad.cdf).pvalue > KS_ALPHA


def test_ks_rejects_a_wrong_distribution():
    # the test has power: planophile samples are not spherical
    theta = lad_by_name("planophile").sample(N_KS, np.random.default_rng(1))
    assert stats.kstest(theta, lad_by_name("spherical").cdf).pvalue < 1e-12


@pytest.mark.parametrize("mean", [10.0, 26.76, 45.0, 57.3, 80.0])
def test_beta_form_has_the_requested_mean_and_passes_ks(mean):
    lad = lad_by_name("spherical").with_mean(mean)
    assert lad.name == "beta"
    assert lad.mean_deg == pytest.approx(mean, abs=1e-12)
    assert lad.mu + lad.nu == pytest.approx(lad_by_name("spherical").concentration)
    theta = lad.sample(N_KS, np.random.default_rng(7))
    assert stats.kstest(theta, lad.cdf).pvalue > KS_ALPHA
    se = theta.std() / math.sqrt(N_KS)
    assert math.degrees(abs(theta.mean() - math.radians(mean))) < 4 * math.degrees(se)


@pytest.mark.parametrize("name", LAD_NAMES)
def test_moment_matched_beta_parameters_match_wang_2007(name):
    lad = lad_by_name(name)
    mu, nu = WANG_2007[name]
    m, _ = lad.moments_t
    k = lad.concentration
    assert k * (1 - m) == pytest.approx(mu, abs=2e-3)
    assert k * m == pytest.approx(nu, abs=2e-3)


def test_shift_moves_only_the_mean_and_clips_to_fixed_at_the_ends():
    pla = lad_by_name("planophile")
    assert pla.shifted(0.0) is pla
    up = pla.shifted(15.0)
    assert up.mean_deg == pytest.approx(pla.mean_deg + 15.0)
    assert up.concentration == pytest.approx(pla.concentration)
    low = pla.shifted(-40.0)
    assert low.name == "fixed" and low.mu == 0.0
    assert np.all(low.sample(5, np.random.default_rng(0)) == 0.0)
    top = lad_by_name("erectophile").shifted(60.0)
    assert top.name == "fixed" and top.mu == pytest.approx(math.pi / 2)


@pytest.mark.parametrize("name", DEWIT)
def test_inverse_cdf_kernel_agrees_with_bisection_reference(name):
    sign = {"planophile": 1.0, "erectophile": -1.0, "plagiophile": -1.0, "extremophile": 1.0}[name]
    freq = {"planophile": 2.0, "erectophile": 2.0, "plagiophile": 4.0, "extremophile": 4.0}[name]
    u = np.concatenate([np.random.default_rng(3).random(2000), [0.0, 1.0, 0.5, 1e-12, 1 - 1e-12]])
    fast = invert_dewit_cdf(name, u)
    ref = invert_dewit_bisection(u, sign, freq)
    lad = lad_by_name(name)
    # equal where the CDF is well conditioned; everywhere, both invert F to machine precision
    np.testing.assert_allclose(lad.cdf(fast), u, atol=4e-16)
    good = lad.pdf(ref) > 1e-3
    np.testing.assert_allclose(fast[good], ref[good], atol=1e-12)


def test_inverse_cdf_rejects_bad_input():
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        invert_dewit_cdf("planophile", np.array([0.5, 1.5]))
    with pytest.raises(ValueError, match="one of"):
        invert_dewit_cdf("spherical", np.array([0.5]))
    with pytest.raises(ValueError, match="1-D"):
        invert_dewit_cdf("planophile", np.zeros((2, 2)))


def test_normals_are_unit_with_uniform_azimuths():
    n = sample_normals(lad_by_name("uniform"), N_KS, np.random.default_rng(5))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    assert np.all(n[:, 2] >= 0)
    az = np.arctan2(n[:, 1], n[:, 0]) % (2 * math.pi)
    assert stats.kstest(az, stats.uniform(0, 2 * math.pi).cdf).pvalue > KS_ALPHA
    theta = np.arccos(n[:, 2])
    assert stats.kstest(theta, lad_by_name("uniform").cdf).pvalue > KS_ALPHA


def test_invalid_distributions_are_errors():
    with pytest.raises(ValueError, match="expected one of"):
        lad_by_name("wavy")
    with pytest.raises(ValueError, match="positive"):
        LeafAngleDistribution("beta", mu=-1.0, nu=2.0)
    with pytest.raises(ValueError, match="view zenith"):
        lad_by_name("spherical").g(2.0)
