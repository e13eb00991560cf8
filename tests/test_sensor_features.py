"""First-echo features against analytic Gaussian echoes and the NumPy reference (docs/method.md §(h))."""

import math

import numba
import numpy as np
import pytest
from reference_sensor import features_reference, make_pulse_table
from scipy.special import erf

from waveforest.constants import RANGE_PER_NS
from waveforest.sensor import FeatureParams, feature_table, first_echo_features
from waveforest.sensor import cfd as cfd_module
from waveforest.sensor import decompose as decompose_module
from waveforest.sensor import features as features_module

FWHM_PER_SD = 2.0 * math.sqrt(2.0 * math.log(2.0))
FWHM_TOL = 0.02  # "FWHM within 2 %"
E_TOL = 0.01  # "E within 1 % of the analytic integral"
NOISE_MEAN = 10.0


def echoes(rng, n, fwhm, amp, sd, dt=1.0, record_ns=256.0, quantise=True):
    s = fwhm / FWHM_PER_SD
    mu = rng.uniform(40.0, 200.0, n)
    t = np.arange(int(round(record_ns / dt))) * dt
    x = NOISE_MEAN + amp * np.exp(-0.5 * ((t[None, :] - mu[:, None]) / s) ** 2) + sd * rng.standard_normal((n, t.size))
    if quantise:
        x = np.clip(np.rint(x), 0, 255)
    return x.astype(np.float32), mu, s


def test_noise_free_gaussians_fwhm_energy_apeak():
    """Noise-free echoes at random sampling phases: FWHM within 2 %, E within 1 % of A s sqrt(2 pi)."""
    rng = np.random.default_rng(1)
    for dt, widths in ((0.5, (2.0, 4.0, 7.2)), (1.0, (4.0, 7.2, 10.1, 14.0)), (2.0, (10.1, 14.0))):
        for fwhm in widths:  # at least 4 samples per FWHM
            for amp in (20.0, 100.0, 230.0):
                x, mu, s = echoes(rng, 100, fwhm, amp, 0.0, dt=dt, quantise=False)
                f = first_echo_features(x, None, dt, mu, NOISE_MEAN, 0.0)
                assert np.abs(f["FWHM"] / fwhm - 1).max() < FWHM_TOL, (dt, fwhm, amp)
                assert np.abs(f["E"] / (amp * s * math.sqrt(2 * math.pi)) - 1).max() < E_TOL, (dt, fwhm, amp)
                assert np.all(f["Npeaks"] == 1)
                # Apeak is the highest sample: never above the true peak, within the sampling loss
                assert np.all(f["Apeak"] <= amp * (1 + 1e-6))
                assert np.all(f["Apeak"] >= amp * math.exp(-0.5 * (dt / 2 / s) ** 2) * (1 - 1e-6))
                assert np.abs(f["t_peak_ns"] - mu).max() < dt / 2


def test_noisy_gaussians_unbiased():
    """Across amplitudes and noise levels (SNR >= 30): mean FWHM within 2 %, mean E within 1 % of the
    analytic integral of the echo above the segment threshold."""
    rng = np.random.default_rng(2)
    for fwhm in (7.2, 10.1, 14.0):
        for amp in (60.0, 120.0, 200.0):
            for sd in (0.5, 1.0, 2.0):
                x, mu, s = echoes(rng, 200, fwhm, amp, sd)
                f = first_echo_features(x, None, 1.0, mu, NOISE_MEAN, sd, segment_sd=3.0)
                assert np.isfinite(f["E"]).all()
                half_span = s * math.sqrt(2 * math.log(amp / (3.0 * sd)))
                e_true = amp * s * math.sqrt(2 * math.pi) * erf(half_span / (s * math.sqrt(2)))
                assert abs(f["E"].mean() / e_true - 1) < E_TOL, (fwhm, amp, sd)
                assert abs(np.nanmean(f["FWHM"]) / fwhm - 1) < FWHM_TOL, (fwhm, amp, sd)
                assert np.mean(f["Npeaks"] == 1) > 0.95  # 2-SD prominence: rare noise peaks on broad echoes


def test_segment_threshold_and_peak_count():
    t = np.arange(256, dtype=float)
    s = 5.0 / FWHM_PER_SD
    g = lambda c, a: a * np.exp(-0.5 * ((t - c) / s) ** 2)  # noqa: E731
    sd = 1.0
    two = NOISE_MEAN + g(100, 80) + g(108, 60)  # deep dip between: two peaks
    shallow = NOISE_MEAN + g(100, 80) + g(104.5, 79)  # dip of ~1 DN: one peak at 2 SD rise
    apart = NOISE_MEAN + g(100, 80) + g(140, 80)  # separate segments: the first only
    f = first_echo_features(np.stack([two, shallow, apart]), None, 1.0, np.array([100.0, 100.0, 100.0]),
                            NOISE_MEAN, sd)
    assert list(f["Npeaks"]) == [2, 1, 1]
    thr = NOISE_MEAN + 3 * sd
    k = np.flatnonzero(apart > thr)
    first_run = k[k < 120]
    assert f["seg_start_ns"][2] == first_run[0] and f["seg_end_ns"][2] == first_run[-1]
    assert f["E"][2] == pytest.approx(np.sum(apart[first_run] - NOISE_MEAN))
    # echo time beside the segment: found within echo_search_ns, else NaN
    f2 = first_echo_features(np.stack([apart, apart]), None, 1.0, first_run[0] - np.array([1.6, 3.6]),
                             NOISE_MEAN, sd, echo_search_ns=2.0)
    assert np.isfinite(f2["Apeak"][0]) and np.isnan(f2["Apeak"][1]) and f2["Npeaks"][1] == 0


@pytest.mark.parametrize("dt", [0.5, 1.0, 2.0])
def test_kernel_matches_reference(dt):
    rng = np.random.default_rng(int(10 * dt))
    n, n_s = 80, int(160 / dt)
    t = np.arange(n_s) * dt
    x = NOISE_MEAN + rng.normal(0, 1.5, (n, n_s))
    te = np.full(n, np.nan)
    for i in range(n):
        cs = rng.uniform(5, 155, rng.integers(1, 4))
        for c in cs:
            x[i] += rng.uniform(3, 120) * np.exp(-0.5 * ((t - c) / (rng.uniform(2, 12) / FWHM_PER_SD)) ** 2)
        te[i] = cs[0] + rng.normal(0, 1.0) if rng.random() > 0.1 else np.nan
    x = np.clip(np.rint(x), 0, 255).astype(np.float32)
    lengths = rng.integers(0, n_s + 1, n)
    x[np.arange(n_s)[None, :] >= lengths[:, None]] = np.nan
    for seg_sd, rise_sd in ((3.0, 2.0), (2.0, 0.5), (5.0, 4.0)):
        f = first_echo_features(x, lengths, dt, te, NOISE_MEAN, 1.5, seg_sd, rise_sd)
        for i in range(n):
            r = features_reference(x[i], lengths[i], dt, NOISE_MEAN, 1.5, te[i], seg_sd, rise_sd)
            for key in ("Npeaks", "Apeak", "FWHM", "E", "seg_start_ns", "seg_end_ns"):
                assert np.allclose(f[key][i], r[key], equal_nan=True, atol=1e-6), (i, key, f[key][i], r[key])


def test_feature_table_heights_and_columns():
    rng = np.random.default_rng(5)
    x, mu, s = echoes(rng, 6, 7.2, 90.0, 1.0)
    mu[5] = np.nan  # no echo time: the pulse's own first CFD echo is used
    anchor = np.column_stack([np.zeros(6), np.zeros(6), np.linspace(120.0, 130.0, 6)])
    d = np.array([0.1, 0.0, -1.0])
    d = d / np.linalg.norm(d)
    table = make_pulse_table(x, echo_time_ns=mu, anchor=anchor, direction=np.tile(d, (6, 1)),
                             extra={"sample_id": [f"s{i}" for i in range(6)], "species": ["birch"] * 6,
                                    "functional_group": ["broadleaf"] * 6, "ground_z": np.full(6, 100.0),
                                    "classification_set": [True] * 6})
    with pytest.warns(UserWarning, match="without an echo time"):
        df = feature_table(table, {"2010_12_1": {"noise_mean": NOISE_MEAN, "noise_sd": 1.0, "fwhm_ns": 7.2}},
                           FeatureParams())
    assert list(df.columns[:7]) == ["dataset", "pulse_id", "source", "sample_id", "species", "functional_group",
                                    "ground_z"]
    for c in ("classification_set", "n_echoes", "Npeaks", "Apeak", "FWHM", "E", "H", "echo_z"):
        assert c in df.columns
    t = df["echo_time_ns"].to_numpy()
    assert np.allclose(t[:5], mu[:5])
    assert np.isfinite(t[5])
    expected_h = anchor[:, 2] + d[2] * t * RANGE_PER_NS - 100.0
    assert np.allclose(df["H"], expected_h)
    assert np.allclose(df["echo_z"], expected_h + 100.0)
    # same features as the array API
    f = first_echo_features(x, None, 1.0, t, NOISE_MEAN, 1.0)
    assert np.allclose(df["E"], f["E"]) and np.allclose(df["Apeak"], f["Apeak"])
    # tuple noise and no ground_z: H is NaN
    df2 = feature_table(make_pulse_table(x[:5], echo_time_ns=mu[:5]), {"2010_12_1": (NOISE_MEAN, 1.0)})
    assert df2["H"].isna().all() and np.allclose(df2["E"], f["E"][:5])
    with pytest.raises(ValueError, match="no noise estimate"):
        feature_table(table, {"other": (1.0, 1.0)})


def test_read_only_inputs_do_not_compile_the_kernels_again():
    """Arrow columns arrive read-only, and Numba types a read-only array apart from a writable
    one: each wrapper copies them, so one call of each kind compiles each kernel once."""
    kernels = (decompose_module._decompose_kernel, features_module._features_kernel, cfd_module.cfd_kernel)
    if numba.config.DISABLE_JIT:
        pytest.skip("kernels run as Python")
    x = np.full((2, 64), 10.0, np.float32)
    x[:, 20:26] += [5.0, 30.0, 60.0, 60.0, 30.0, 5.0]
    counts = []
    for frozen in (False, True):
        args = [x.copy(), np.full(2, 64), np.ones(2), np.full(2, 22.0), np.full(2, 10.0), np.ones(2)]
        for a in args:
            a.flags.writeable = not frozen
        samples, lengths, dt, te, mean, sd = args
        decompose_module.decompose(samples, lengths, dt, mean, sd, pulse_fwhm_ns=4.0)
        features_module.first_echo_features(samples, lengths, dt, te, mean, sd)
        cfd_module.detect_echoes(samples, lengths, dt, mean, sd, fwhm_ns=4.0)
        counts.append([len(k.signatures) for k in kernels])
    assert counts[1] == counts[0]
