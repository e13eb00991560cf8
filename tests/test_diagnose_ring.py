"""The rings around the compared trees (diagnose.ring_m): a stratum chosen by the beam's
geometry, split by the first echo, and mirrored on the twins (docs/method.md §(j))."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pyarrow as pa
import pytest
from fixtures.tables import pulse_table
from test_analysis_select import FIELDS
from test_diagnose_run import _strata

from waveforest.diagnose.strata import RING, apply_rules, pulse_keys, with_ring_pulses
from waveforest.diagnose.twins import StudySimulator
from waveforest.model.selection import SelectRules, match_rings, ring_pulses, select_pulses

RULES = SelectRules(tree_radius_m=0.5, tree_min_echo_h_m=1.0, min_pulses=1)
TILT = np.radians(20.0)

NADIR = [
    [(0.6, 0.0, 100.1)],   # 0: ground 0.6 m from T1 (birch 3 m, compared): ring, low
    [(0.0, 0.65, 102.5)],  # 1: crown edge 0.65 m from T1: no sample takes it: ring, high
    [(0.3, 0.3, 102.0)],   # 2: taken by T1 (tree rule)
    [(0.1, 0.0, 100.5)],   # 3: taken as below T1's crown
    [(0.85, 0.0, 100.1)],  # 4: beyond the ring
    [(0.8, 0.0, 100.1)],   # 5: on the outer radius: outside (the ring is [inner, outer))
    [(0.0, 10.6, 100.1)],  # 6: the ring of T2, a birch of 6 m that is not compared
    [(0.0, 0.5, 100.1)],   # 7: low echo on the inner radius: below T1's crown (select takes it)
]


def _oblique(table: pa.Table, ground_xyz, sign: float) -> pa.Table:
    """``table``'s one pulse turned into a beam tilted 20 deg in x (dir x = sign sin 20 deg)
    through the point ``ground_xyz``; its echoes stay where they are."""
    d = np.array([sign * np.sin(TILT), 0.0, -np.cos(TILT)])
    sensor = np.asarray(ground_xyz, float) - 1000.0 * d
    for name, value in (*((f"sensor_{a}", sensor[i]) for i, a in enumerate("xyz")),
                        *((f"dir_{a}", d[i]) for i, a in enumerate("xyz"))):
        table = table.set_column(table.schema.get_field_index(name), name, pa.array([float(value)]))
    return table


def _on_beam(ground_xyz, sign: float, z: float):
    """The point at height ``z`` on the beam of :func:`_oblique`."""
    x0, y0, z0 = ground_xyz
    return (x0 - sign * np.tan(TILT) * (z - z0), y0, z)


def test_ring_membership_is_exact_on_nadir_beams():
    out = ring_pulses(pulse_table("2010_12_1", NADIR), FIELDS, 2010, RULES, 0.8).to_pandas().set_index("pulse_id")
    assert out.index.tolist() == [0, 1]
    assert (out["sample_id"] == "T1").all() and (out["species"] == "birch").all() and out["ring_set"].all()
    assert not out[["single_echo_set", "classification_set", "comparison_set", "below_crown_set"]].any().any()
    assert out["sample_distance_m"].tolist() == pytest.approx([0.6, 0.65])
    assert out["first_echo_h_m"].tolist() == pytest.approx([0.1, 2.5])
    taken = select_pulses(pulse_table("2010_12_1", NADIR), FIELDS, 2010, RULES).column("pulse_id").to_pylist()
    assert not set(taken) & set(out.index)


def test_the_ring_is_a_rule_on_the_beam_at_the_tree_s_own_ground():
    """An oblique beam belongs to the ring where it meets the tree's ground, wherever its echo
    lies; a tree on higher ground is met at its own height."""
    fields = pd.concat([FIELDS, FIELDS.iloc[[0]].assign(sample_id="T3", x=5.0, ground_z=102.0)], ignore_index=True)
    cases = [((0.7, 0.0, 100.0), -1.0, 103.0, "T1"),   # echo 3 m up lies 1.8 m out: no sample takes it
             ((0.7, 0.0, 100.0), 1.0, 103.0, None),    # echo 3 m up lies 0.4 m from T1: the tree takes it
             ((5.7, 0.0, 102.0), -1.0, 102.1, "T3"),   # 0.7 m from T3 at 102 m; 1.4 m at 100 m
             ((0.3, 0.0, 100.0), -1.0, 103.0, None)]   # meets the ground inside the tree radius
    for ground, sign, z, expected in cases:
        table = _oblique(pulse_table("2010_12_1", [[_on_beam(ground, sign, z)]]), ground, sign)
        out = ring_pulses(table, fields, 2010, RULES, 0.8)
        assert out.column("sample_id").to_pylist() == ([expected] if expected else []), (ground, sign)
        if expected:
            assert out.column("sample_distance_m").to_pylist() == pytest.approx([0.7])
    trees = fields.iloc[[0, 5]].reset_index(drop=True)
    table = _oblique(pulse_table("2010_12_1", [[_on_beam((5.7, 0.0, 102.0), -1.0, 102.1)]]), (5.7, 0.0, 102.0), -1.0)
    assert match_rings(table, trees, 0.5, 0.8)[0].tolist() == [1]
    assert match_rings(table, trees.assign(ground_z=100.0), 0.5, 0.8)[0].tolist() == [-1]


def test_ring_pulses_join_the_select_table_once_and_become_a_stratum():
    nadir = pulse_table("2010_12_1", NADIR)
    selected = select_pulses(nadir, FIELDS, 2010, RULES)
    strata = _strata(ring_m=0.8)
    table = with_ring_pulses(selected, nadir, FIELDS, 2010, strata)
    assert table.num_rows == selected.num_rows + 2
    twice = with_ring_pulses(table, nadir, FIELDS, 2010, strata)
    assert twice.num_rows == table.num_rows
    keys = pulse_keys({"2010_12_1": table}, strata).set_index("pulse_id")["stratum"]
    assert keys.loc[[0, 1]].tolist() == [RING, RING] and (keys.drop([0, 1]) != RING).all()
    assert RING not in pulse_keys({"2010_12_1": table}, _strata(ring_m=None))["stratum"].tolist()


def test_apply_rules_keeps_the_ground_beside_the_tree_on_both_sides():
    """Rows of the ring whose first echo lies at or above select.tree_min_echo_h_m (the crown's
    edge) are dropped, real and twin alike; the low ones stay, not dropped by the tree's height
    rule, keep Apeak and E, which compare's height rule blanks on a crown pulse, and lose H,
    Npeaks and FWHM."""
    strata = _strata(ring_m=0.8)
    lo, hi = strata.rules.tree_min_echo_h_m, strata.compare_min_h_m["birch"]
    feats = pd.DataFrame({"species": "birch", "is_tree": True, "stratum": ["", "", RING, RING, RING],
                          "H": [lo - 0.1, hi - 0.1, lo - 0.1, lo + 0.1, np.nan], "E": 500.0, "Apeak": 60.0,
                          "FWHM": 7.0, "Npeaks": 1.0})
    out = apply_rules(feats, strata)
    assert out["stratum"].tolist() == ["", RING] and out["H"].iloc[0] == pytest.approx(hi - 0.1)
    assert out["E"].isna().tolist() == [True, False] and out["Apeak"].isna().tolist() == [True, False]
    # the ground beside compares the return's strength only (RING_BLANKED)
    assert out.loc[1, ["H", "Npeaks", "FWHM"]].isna().all()


def test_a_twin_whose_first_echo_a_sample_would_take_leaves_the_ring():
    """The mirror of the rule that kept the real pulse out of the samples: the twin of a ring
    pulse is dropped when its own first echo lies within select.tree_radius_m of the stem."""
    ground = (0.7, 0.0, 100.0)
    table = pa.concat_tables([_oblique(pulse_table("2010_12_1", [[_on_beam(ground, 1.0, 100.1)]], pulse_ids=[i]),
                                       ground, 1.0) for i in range(2)])
    rows = ring_pulses(table, FIELDS, 2010, RULES, 0.8)
    assert rows.num_rows == 2  # both real first echoes lie on the ground 0.66 m out
    twins = pd.DataFrame({"pulse_id": [1, 0], "echo_z": [103.0, 100.1], "H": [3.0, 0.1]})  # twin 1 hits the crown
    fake = SimpleNamespace(_features=lambda *a, **k: twins, strata=_strata(ring_m=0.8))
    kept = StudySimulator._ring(fake, rows, "2010_12_1", {}, None)
    assert [f["pulse_id"].tolist() for f in kept] == [[0]]


def test_rings_without_the_pulse_tables_are_a_clear_error():
    from waveforest.errors import WaveforestError
    from waveforest.stages.diagnose import with_added_strata

    with pytest.raises(WaveforestError, match=r"diagnose\.ring_m: the AGC-normalised pulse tables \(--agc\)"):
        with_added_strata({"2010_12_1": None}, None, FIELDS, None, {}, _strata(ring_m=0.8))
