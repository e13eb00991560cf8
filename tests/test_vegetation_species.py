"""Species table, parameter files and the build_scene contract for every species."""

import re

import numpy as np
import pandas as pd
import pytest

from waveforest.errors import WaveforestError
from waveforest.scene import Scene
from waveforest.vegetation import build, build_scene, species_table
from waveforest.vegetation.params import RES, UnknownSpeciesError, species_params

SLUGS = [
    "scots_pine", "norway_spruce", "birch", "european_aspen", "european_mountain_ash", "gray_alder",
    "goat_willow", "other_willows", "common_juniper", "fireweed", "raspberry", "western_brackenfern",
    "reedgrass", "wavy_hairgrass", "fresh_grass_low", "fresh_grass_high", "heather", "reindeer_lichens",
    "whortleberry", "lingonberry", "black_crowberry", "marsh_labrador_tea", "schrebers_big_red_stem_moss",
    "mosses_misc", "ripening_grass", "stone_surface", "mineral_soil", "logging_residue", "sand_road",
]
PAPER_TABLE1 = "/work/shared/paper/table1_species.csv"


def test_species_table_lists_table1_with_the_contract_columns():
    t = species_table()
    assert list(t["slug"]) == SLUGS
    for col in ("slug", "name", "scientific_name", "functional_group", "model", "min_h", "max_h",
                "is_tree", "reference_surface"):
        assert col in t.columns
    t1 = pd.read_csv(RES / "table1_species.csv")
    assert list(t["name"]) == list(t1["species"])
    assert set(t["functional_group"]) == {"conifer", "broadleaf", "low_green", "low_barren_abiotic"}
    assert list(t.loc[t["is_tree"], "functional_group"].unique()) == ["conifer", "broadleaf"]
    assert list(t.loc[t["reference_surface"], "slug"]) == ["sand_road"]
    assert list(t.loc[t["paper_model"], "slug"]) == ["birch", "fireweed", "raspberry"]
    assert t.loc[t.slug == "birch", "model"].item() == "tree"


def test_shipped_table1_is_the_papers():
    try:
        paper = pd.read_csv(PAPER_TABLE1)
    except FileNotFoundError:
        pytest.skip("shared paper tables not present")
    pd.testing.assert_frame_equal(pd.read_csv(RES / "table1_species.csv"), paper)


def test_every_number_has_a_source_and_every_cited_key_exists():
    refs = set(pd.read_csv(RES / "references.csv", comment="#")["key"])
    st = pd.read_csv(RES / "structure.csv", comment="#")
    sp = pd.read_csv(RES / "species.csv", comment="#")
    sources = list(st["source"]) + list(sp["optics_source"])
    assert all(isinstance(s, str) and s.strip() for s in sources)
    cited = {k for s in sources for k in re.findall(r"\b([a-z]+\d{4})\b", s)}
    assert cited and cited <= refs, f"unknown reference keys {cited - refs}"


def _heights(row):
    lo = max(row.min_h, 0.0)
    return sorted({lo, row.max_h})


@pytest.mark.parametrize("row", list(species_table().itertuples(index=False)), ids=SLUGS)
def test_every_species_builds_a_valid_plot_with_its_top_at_the_field_height(row):
    for h in _heights(row):
        b = build(row.slug, h, seed=11)
        s = b.scene
        assert isinstance(s, Scene) and len(s) > 0
        lo, hi = s.bounds
        # inside the 6 x 6 m plot up to one element: a leaf, a grass blade's reach, half a
        # stem segment (positions wrap by element base); residue pieces up to half their length
        margin = 0.8 if row.slug == "logging_residue" else 0.5
        assert lo[0] >= -3 - margin and hi[0] <= 3 + margin
        assert lo[1] >= -3 - margin and hi[1] <= 3 + margin
        assert np.all(s.rho + s.tau <= 1.0 + 1e-6)
        kinds = set(np.unique(s.kind))
        if row.model in ("surface",):
            assert np.all(s.tau == 0)
            # mean surface at max(h, carpet) (0 for bare ones); a Gaussian relief's maximum over
            # ~14,000 grid points lies between 0 and 5 RMS
            p = species_params(row.slug)
            level = max(h, p["carpet_min_m"]) if p["carpet_min_m"] > 0 else 0.0
            assert level <= hi[2] <= level + 5 * p["relief_rms_m"]
        else:
            assert 1 in kinds and 0 in kinds
            assert hi[2] >= h - 0.01, "the tallest plant reaches the field height"
            assert hi[2] <= h + b.element_size_m + 1e-3, "nothing rises above h by more than one element"
            assert b.leaf_area_m2 == pytest.approx(b.target_leaf_area_m2, rel=1e-6)
            assert s.areas[s.kind == 1].sum() == pytest.approx(b.target_leaf_area_m2, rel=2e-3)


@pytest.mark.parametrize("slug,h", [("birch", 3.0), ("raspberry", 1.2), ("scots_pine", 4.0),
                                    ("heather", 0.3), ("sand_road", 0.0)])
def test_same_seed_gives_the_identical_scene_and_another_seed_another(slug, h):
    a, b, c = build_scene(slug, h, 5), build_scene(slug, h, 5), build_scene(slug, h, 6)
    for name in ("triangles", "rho", "tau", "kind"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.triangles.shape != c.triangles.shape or not np.array_equal(a.triangles, c.triangles)


def test_paper_optics_and_ground_plane():
    # docs/method.md §(g): leaves 0.47/0.50; birch wood 0.50/0; raspberry and fireweed shoots 0.47/0;
    # Lambertian ground plane rho 0.30, tau 0
    for slug, h, wood in (("birch", 3.0, 0.50), ("raspberry", 1.0, 0.47), ("fireweed", 1.2, 0.47)):
        s = build_scene(slug, h, 1)
        leaf, w, g = s.kind == 1, s.kind == 2, s.kind == 0
        assert np.all(s.rho[leaf] == np.float32(0.47)) and np.all(s.tau[leaf] == np.float32(0.50))
        assert np.all(s.rho[w] == np.float32(wood)) and np.all(s.tau[w] == 0)
        assert g.sum() == 2 and np.all(s.triangles[g][:, :, 2] == 0)
        assert np.all(s.rho[g] == np.float32(0.30)) and np.all(s.tau[g] == 0)
        assert s.areas[g].sum() == pytest.approx(36.0)
        assert np.all(s.normals[g][:, 2] == 1.0)
    s = build_scene("birch", 3.0, 1, ground_rho=0.12)
    assert np.all(s.rho[s.kind == 0] == np.float32(0.12))


def test_ground_false_removes_the_ground_and_bare_surfaces_refuse_it():
    s = build_scene("birch", 3.0, 1, ground=False)
    assert 0 not in s.kind
    s = build_scene("logging_residue", 0.5, 1, ground=False)
    assert 0 not in s.kind and 2 in s.kind
    with pytest.raises(WaveforestError, match="bare surface"):
        build_scene("sand_road", 0.0, 1, ground=False)


def test_bad_specs_are_clear_errors():
    with pytest.raises(UnknownSpeciesError, match="unknown; expected one of scots_pine, .*sand_road"):
        build_scene("oak", 3.0, 1)
    assert issubclass(UnknownSpeciesError, WaveforestError)
    with pytest.raises(WaveforestError, match=r"height 40.0 m for birch: expected 0.5 to 12 m"):
        build_scene("birch", 40.0, 1)
    with pytest.raises(WaveforestError, match="height"):
        build_scene("raspberry", -1.0, 1)
    with pytest.raises(WaveforestError, match="height"):
        build_scene("raspberry", float("nan"), 1)
    with pytest.raises(WaveforestError, match="seed"):
        build_scene("birch", 3.0, -2)
    with pytest.raises(WaveforestError, match="lai_jitter"):
        build_scene("birch", 3.0, 1, lai_jitter=0.9)
    with pytest.raises(WaveforestError, match="leaf_albedo"):
        build_scene("birch", 3.0, 1, leaf_albedo=0.0)
    with pytest.raises(WaveforestError, match="mean_leaf_angle"):
        build_scene("birch", 3.0, 1, mean_leaf_angle=95.0)
    with pytest.raises(WaveforestError, match="leaf_rho"):
        build_scene("birch", 3.0, 1, leaf_rho=1.5)
    with pytest.raises(WaveforestError, match="<= 1"):
        build_scene("birch", 3.0, 1, leaf_rho=0.6, leaf_tau=0.5)


def test_a_typo_in_the_parameter_files_names_the_file_species_and_parameter(tmp_path, monkeypatch):
    import shutil

    from waveforest.vegetation import params

    copy = tmp_path / "vegetation"
    shutil.copytree(RES, copy)
    st = (copy / "structure.csv").read_text().replace("birch,petiole_m,", "birch,petiol_m,")
    (copy / "structure.csv").write_text(st)
    monkeypatch.setattr(params, "RES", copy)
    params._tables.cache_clear()
    try:
        with pytest.raises(params.ParameterFileError, match=r"structure.csv: birch \(tree\): missing \['petiole_m'\], unexpected \['petiol_m'\]"):
            params.species_params("birch")
    finally:
        params._tables.cache_clear()
