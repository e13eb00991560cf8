"""Whole-waveform statistics of waveforest.diagnose: analytic values on Gaussian echoes."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pytest
from fixtures.tables import pulse_table
from scipy.stats import norm

from waveforest.constants import RANGE_PER_NS
from waveforest.diagnose.gap import ALL_FEATURES, DEFAULT_FEATURES, FEATURE_SD_FLOOR, FEATURES
from waveforest.diagnose.waveform import (
    PROFILE_FEATURES,
    WAVEFORM_FEATURES,
    waveform_statistics,
    with_waveform_statistics,
)
from waveforest.errors import WaveforestError

FWHM_NS = 7.0
SIGMA_M = FWHM_NS / (2 * np.sqrt(2 * np.log(2))) * RANGE_PER_NS  # an echo's SD along z, m
NOISE = {"d": {"noise_mean": 10.0, "noise_sd": 0.01}}


def _pulses(echoes, amplitudes, n_samples=480, sampling_ns=0.25):
    """Nadir pulses, each a sum of Gaussian echoes at the given heights (ground at z = 0)."""
    tables = []
    for z, a in zip(echoes, amplitudes):
        parts = [pulse_table("d", [[(0.0, 0.0, zz)]], amplitude=aa, fwhm_ns=FWHM_NS, n_samples=n_samples,
                             sampling_ns=sampling_ns, pre_m=6.0 + z[0] - zz) for zz, aa in zip(z, a)]
        wf = np.sum([np.asarray(p.column("samples")[0].as_py()) - 10.0 for p in parts], axis=0) + 10.0
        t = parts[0].set_column(parts[0].schema.get_field_index("samples"), "samples",
                                pa.array([wf.astype(np.float32)], pa.list_(pa.float32())))
        tables.append(t)
    t = pa.concat_tables(tables)
    t = t.set_column(t.schema.get_field_index("pulse_id"), "pulse_id", pa.array(np.arange(t.num_rows), pa.int64()))
    return t.append_column("ground_z", pa.array(np.zeros(t.num_rows)))


def test_two_echoes_give_the_analytic_profile_depth_and_median():
    """A crown echo at 3.5 m of twice the ground echo's energy, the ground at 0 m."""
    t = _pulses([(3.5, 0.0)], [(160.0, 80.0)])
    first = pd.DataFrame({"echo_z": [3.5]})
    s = waveform_statistics(t, NOISE, first).iloc[0]
    crown, ground = 2 / 3, 1 / 3
    assert sum(s[f] for f in PROFILE_FEATURES) == pytest.approx(1.0)
    assert s["E_h4"] == pytest.approx(crown * norm.cdf(0.5 / SIGMA_M), abs=0.01)  # above 3 m
    assert s["E_h0"] == pytest.approx(ground * norm.cdf(0.25 / SIGMA_M), abs=0.01)  # below 0.25 m
    assert s["E_below"] == pytest.approx(ground, abs=0.01)  # more than 1 m below the first echo
    assert s["D_mean"] == pytest.approx(ground * 3.5, abs=0.02)
    # half of the energy lies above the height where the crown echo's CDF reaches 3/4
    assert s["H_median"] == pytest.approx(3.5 - norm.ppf(0.75) * SIGMA_M, abs=0.03)


def test_statistics_do_not_change_with_the_gain_and_follow_a_lower_return():
    t = _pulses([(3.0, 0.0), (3.0, 0.0), (3.0, 0.8)], [(100.0, 50.0), (170.0, 85.0), (100.0, 50.0)])
    s = waveform_statistics(t, NOISE, pd.DataFrame({"echo_z": [3.0, 3.0, 3.0]}))
    for f in WAVEFORM_FEATURES:  # gain 1.7: same shares and heights
        assert s[f].iloc[1] == pytest.approx(s[f].iloc[0], abs=2e-3), f
    # the lower echo raised from the ground to 0.8 m (an understory): less energy below 0.25 m, less depth
    assert s["E_h0"].iloc[2] < s["E_h0"].iloc[0] - 0.1
    assert s["E_h2"].iloc[2] > s["E_h2"].iloc[0] + 0.1
    assert s["D_mean"].iloc[2] == pytest.approx(s["D_mean"].iloc[0] - 0.8 / 3, abs=0.02)


def test_a_pulse_without_signal_gives_nan_and_rows_join_by_pulse_id():
    t = _pulses([(3.0, 0.0), (3.0, 0.0)], [(100.0, 50.0), (0.0, 0.0)])
    s = waveform_statistics(t, NOISE, pd.DataFrame({"echo_z": [3.0, np.nan]}))
    assert s.loc[1, WAVEFORM_FEATURES].isna().all() and s.loc[0, WAVEFORM_FEATURES].notna().all()
    feats = pd.DataFrame({"dataset": ["d", "d"], "pulse_id": [1, 0], "echo_z": [np.nan, 3.0], "H": [0.0, 3.0]})
    joined = with_waveform_statistics(feats, {"d": t}, NOISE)
    assert joined["pulse_id"].tolist() == [1, 0] and joined["H"].tolist() == [0.0, 3.0]
    assert joined.loc[1, "E_below"] == pytest.approx(s.loc[0, "E_below"])
    with pytest.raises(WaveforestError, match="without a pulse"):
        with_waveform_statistics(feats.assign(pulse_id=[5, 0]), {"d": t}, NOISE)
    with pytest.raises(WaveforestError, match="noise"):
        waveform_statistics(t, {}, pd.DataFrame({"echo_z": [3.0, 3.0]}))


def test_every_statistic_has_a_floor_and_the_default_gap_is_the_first_echo_s():
    assert DEFAULT_FEATURES == FEATURES and ALL_FEATURES == FEATURES + WAVEFORM_FEATURES
    assert all(FEATURE_SD_FLOOR[f] > 0 for f in ALL_FEATURES)
