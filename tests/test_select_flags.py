"""select's single_echo_set: the per-pulse part of the classification rule (docs/method.md §(i4))."""

from __future__ import annotations

from fixtures.tables import pulse_table
from test_analysis_select import ECHOES, FIELDS

from waveforest.model.selection import SelectRules, select_pulses


def test_single_echo_set_is_one_dr_echo_outside_below_crown():
    rules = SelectRules(tree_radius_m=0.5, tree_min_echo_h_m=1.0, min_pulses=3)
    out = select_pulses(pulse_table("2010_12_1", ECHOES), FIELDS, 2010, rules).to_pandas().set_index("pulse_id")
    # 7 has two DR echoes; 2 has one, but lies below T1's crown (below_crown_set)
    assert out.index[out["single_echo_set"]].tolist() == [0, 3, 4, 8, 9]
    assert out.loc[2, "below_crown_set"] and out.loc[2, "n_echoes"] == 1
    # classification_set: the rule counted within this dataset (birch has 2 < 3 such pulses)
    assert out.index[out["classification_set"]].tolist() == [3, 4, 8]
    assert not (out["classification_set"] & ~out["single_echo_set"]).any()
