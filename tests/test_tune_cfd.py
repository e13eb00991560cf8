"""``tune-cfd``: noise, system pulse width and CFD from a pulse table alone.

Truths: analytic Gaussian echoes of known width and noise; hand-counted agreement shares; the
virtual campaign's own DR discriminator and noise (truth.json); the real RIEGL file's
within_0_10_m printed by the command.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from waveforest import config
from waveforest.cli import main
from waveforest.sensor.self_calibration import (
    dr_agreement,
    dr_visible,
    flat_top,
    system_fwhm,
    tail_noise,
)

SIGMA_PER_FWHM = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


def _gaussians(n, fwhm_ns, amp, mu_ns, *, dt=1.0, n_samples=120, noise=(10.0, 1.5), seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples) * dt
    s = np.asarray(fwhm_ns, dtype=float)[:, None] * SIGMA_PER_FWHM if np.ndim(fwhm_ns) else fwhm_ns * SIGMA_PER_FWHM
    x = np.asarray(amp, dtype=float).reshape(-1, 1) * np.exp(-0.5 * ((t[None, :] - np.asarray(mu_ns).reshape(-1, 1)) / s) ** 2)
    return np.round(x + noise[0] + noise[1] * rng.standard_normal((n, n_samples))).astype(np.float32)


def test_tail_noise_leaves_out_echo_tails_and_weak_echoes():
    n = 400
    mu = np.full(n, 90.0)  # echoes late in the record: their tails fall into the last 50 samples
    x = _gaussians(n, 6.0, 150.0, mu, seed=1)
    x[::10, 110:113] += 30  # weak unreported echoes in the tail
    st = tail_noise(x, np.full(n, 120), 1.0, mu, tail=50, guard_ns=15.0, clip_sd=4.0)
    assert st.mean == pytest.approx(10.0, abs=0.05)
    assert st.sd_analog == pytest.approx(1.5, rel=0.05)
    assert st.n_pulses == n and st.n_samples < n * 15  # only samples 105..119, less the clipped ones
    naive = x[:, -50:]
    assert naive.mean() > 10.5  # what the plain tail would give


def test_system_fwhm_is_the_narrowest_mode_of_single_echoes():
    rng = np.random.default_rng(2)
    planar = 5.0 + 0.15 * rng.standard_normal(600)
    wide = 5.0 * (1.0 + rng.exponential(0.6, 900))  # vegetation: wider, more of them
    est = system_fwhm(np.concatenate([planar, wide]))
    assert est.fwhm_ns == pytest.approx(5.0, abs=0.1)
    assert not np.isfinite(system_fwhm(planar[:5]).fwhm_ns)


def test_flat_top_and_dr_visibility():
    x = np.array([[0, 1, 5, 9, 9, 2, 0], [0, 1, 5, 9, 3, 2, 0], [0, 0, 0, 0, 0, 0, 0]], np.float32)
    np.testing.assert_array_equal(flat_top(x, None), [True, False, False])
    vis = dr_visible(x, None, 1.0, np.array([3.0, 0.0, np.nan]), 4.0, 0.5)  # +- 0.5 ns and one sample
    np.testing.assert_array_equal(vis, [True, False, False])


def test_dr_agreement_counts_over_all_pulses_with_a_dr_echo():
    dr = np.array([0.01, -0.05, 0.30, 5.0, np.nan, 3.0, 0.0, np.nan])
    res = dr.copy()
    has = np.array([1, 1, 1, 1, 1, 1, 1, 0], bool)
    vis = np.array([1, 1, 1, 1, 1, 0, 1, 0], bool)
    a = dr_agreement(dr, res, has, vis)
    assert a["n_pulses"] == 7 and a["n_gated"] == 4
    assert a["within_0_10_m"] == pytest.approx(3 / 7)
    assert a["within_0_10_m_gated"] == pytest.approx(3 / 4)
    lim = {k: v["n"] for k, v in a["limits"].items()}
    assert lim == {"no_cfd_echo": 1, "dr_below_noise": 1, "other_echo": 1, "same_echo_off": 1}


@pytest.fixture(scope="module")
def riegl_pulses(tmp_path_factory):
    """The bundled real RIEGL file (tests/data/real/README.md) as ``ingest`` writes it."""
    from reference_io import RIEGL

    from waveforest.io.las.pulses import las_to_pulses as ingest

    out = tmp_path_factory.mktemp("riegl") / "riegl.parquet"
    ingest(RIEGL, out, agc_attribute=None)
    return out


def test_tune_cfd_on_the_real_riegl_file(riegl_pulses, tmp_path, capsys):
    out, png = tmp_path / "cfd.json", tmp_path / "cfd.png"
    main(["tune-cfd", str(riegl_pulses), "--out", str(out), "--plot", str(png), "--no-progress"])
    res = json.loads(out.read_text())
    line = capsys.readouterr().out
    assert "within 0.10 m of the DR echo" in line and str(out) in line
    for key in ("noise_mean", "noise_sd", "system_fwhm_ns", "fraction", "delay_ns", "within_0_10_m",
                "median_residual_m", "n_pulses", "within_0_10_m_gated"):
        assert res[key] is not None, key
    assert res["n_pulses"] == 2368  # every pulse of the file has a DR echo; the share counts them all
    # measured (docs/own-data.md): 98.0 % within 0.10 m, median residual < 1 mm
    assert res["within_0_10_m"] >= 0.95 and abs(res["median_residual_m"]) < 0.02
    assert 3.5 < res["system_fwhm_ns"] < 5.5  # the RIEGL's own pulse-width attribute: 4-5 ns
    assert png.stat().st_size > 10_000


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    """A small virtual campaign with vegetation (one dataset, ~3,600 pulses; 15-25 s: slow)."""
    pytest.importorskip("waveforest.vegetation")
    from waveforest.campaign import run as synthesize
    from waveforest.io.las.pulses import las_to_pulses as ingest
    from waveforest.settings import campaign_settings

    tmp = tmp_path_factory.mktemp("campaign")
    cfg = config.validate(yaml.safe_load(yaml.safe_dump(
        {"seed": 5, "datasets": ["2010_12_1"], "campaign": {"samples_per_species": 2, "n_rays": 300, "max_order": 3}})))
    synthesize(campaign_settings(cfg), tmp / "c", progress=False)
    ingest(tmp / "c" / "2010_12_1.las", tmp / "p.parquet", dataset="2010_12_1")
    return cfg, json.loads((tmp / "c" / "truth.json").read_text()), tmp / "p.parquet"


@pytest.mark.slow
def test_tuned_cfd_recovers_the_campaigns_dr_discriminator(campaign, tmp_path):
    """The campaign's DR discriminator is known there (truth.json): the tuned CFD's width term
    ln(f)/delay lies within 10 % of it (as for calibrate, docs/validation.md), the noise and the
    pulse width are the sensor's, and the paper's criterion holds."""
    from waveforest.stages import tune_cfd

    cfg, truth, pulses = campaign
    res = tune_cfd.run(pulses, tmp_path / "cfd.json", cfg, progress=False)
    sensor = truth["datasets"]["2010_12_1"]["sensor"]
    dr = sensor["dr_cfd"]
    assert res["cfd_tuning"]["tuned"], res["cfd_tuning"]["reason"]
    term = math.log(res["fraction"]) / res["delay_ns"]
    assert term == pytest.approx(math.log(dr["fraction"]) / dr["delay_ns"], rel=0.10)
    assert res["noise_mean"] == pytest.approx(sensor["noise_mean_dn"], abs=0.1)
    assert res["noise_sd_analog"] == pytest.approx(sensor["noise_sd_dn"], rel=0.05)
    assert res["system_fwhm_ns"] == pytest.approx(sensor["pulse_fwhm_ns"], rel=0.05)
    assert res["within_0_10_m"] >= 0.95 and abs(res["median_residual_m"]) < 0.02
