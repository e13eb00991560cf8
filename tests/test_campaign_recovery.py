"""The analysis recovers the campaign's hidden sensor truth: AGC b (Eq. 1), S(t) (Eq. 8) and the
DR discriminator that the CFD is tuned to (docs/method.md §(f)).

Full pulse density on the reference targets of two datasets, through the real pipeline
stages (``ingest``, ``agc``, ``calibrate``); about 10 s, and 20 s for the CFD on a campaign
with vegetation.

A target flown by two strips is seen at two ranges and incidence angles (a few % of
amplitude) and, independently, at two AGC levels (the loop follows each strip's own
terrain). The pooled within-target CV of docs/method.md §(b) reads that amplitude difference as
AGC gain and biases b (about -11 % in 2010_12_1 at seed 3). The ``agc`` stage nests the
strips within the targets (groups = target passes, told apart by gaps in GPS time,
``agc.pass_gap_s``), which removes the bias (:func:`test_agc_stage_recovers_the_true_b`);
:func:`test_nested_cv_with_strips_recovers_the_true_b` checks the same with the sensor
module's ``fit_b`` and an independent strip split of the whole dataset.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from waveforest import config

B_TOL = 0.05
"""The issue's criterion: fitted b within 5 % of the manifest's."""

S_TOL = 0.03
"""The issue's criterion: recovered S(t) within 3 % (relative L2) of the manifest's."""

DATASETS = ["2010_12_1", "2012_10_1"]


def _campaign_through_calibrate(tmp, campaign: dict):
    """A virtual campaign (seed 3, ``campaign`` section) through ingest, agc and calibrate:
    (truth, {dataset: (agc fit, calibration JSON, S(t) path, pulse table, targets.csv)})."""
    pytest.importorskip("waveforest.vegetation")
    from waveforest.campaign import run
    from waveforest.io.las.pulses import las_to_pulses as ingest
    from waveforest.io.tables import read_datasets, read_targets
    from waveforest.settings import campaign_settings
    from waveforest.stages import agc as agc_stage
    from waveforest.stages import calibrate as calibration

    cfg = config.validate(yaml.safe_load(yaml.safe_dump({"seed": 3, "datasets": DATASETS, "campaign": campaign})))
    camp = tmp / "campaign"
    run(campaign_settings(cfg), camp, progress=False)
    truth = json.loads((camp / "truth.json").read_text())
    targets, datasets = read_targets(camp / "targets.csv"), read_datasets(camp / "datasets.csv")
    out = {}
    for ds in DATASETS:
        pulses = tmp / f"{ds}.parquet"
        ingest(camp / f"{ds}.las", pulses, dataset=ds, trajectory=camp / f"{ds}_trajectory.csv")
        fit = agc_stage.run(pulses, targets, datasets, tmp / f"{ds}_agc.parquet", tmp / f"{ds}_agc.json", cfg,
                            progress=False)
        cal = calibration.run(tmp / f"{ds}_agc.parquet", targets, datasets, tmp / f"{ds}_S.parquet",
                              tmp / f"{ds}_S.json", cfg, progress=False)
        out[ds] = (fit, cal, tmp / f"{ds}_S.parquet", pulses, camp / "targets.csv")
    return truth, out


@pytest.fixture(scope="module")
def recovered(tmp_path_factory):
    """Targets only (one sand-road sample per year)."""
    return _campaign_through_calibrate(tmp_path_factory.mktemp("recovery"),
                                       {"samples_per_species": 1, "species": ["sand_road"], "n_rays": 500})


@pytest.mark.parametrize("ds", DATASETS)
def test_agc_stage_recovers_the_true_b(recovered, ds):
    truth, out = recovered
    fit = out[ds][0]
    d = truth["datasets"][ds]
    assert fit.a == pytest.approx(d["a"], abs=1e-6)
    assert fit.b == pytest.approx(d["b"], rel=B_TOL)


STRIP_GAP_S = 60.0
"""Pulses more than this apart in GPS time belong to different strips (turns take 90 s)."""


@pytest.mark.parametrize("ds", DATASETS)
def test_nested_cv_with_strips_recovers_the_true_b(recovered, ds):
    from waveforest.io.pulses import list_to_padded, read_pulses
    from waveforest.io.tables import read_targets
    from waveforest.sensor import fit_b, peak_amplitudes, pulse_targets

    truth, out = recovered
    d = truth["datasets"][ds]
    pulses = read_pulses(out[ds][3])
    targets = read_targets(out[ds][4])
    tidx = pulse_targets(pulses, targets, d["year"])
    on = tidx >= 0
    on[on] = targets["agc"].to_numpy(dtype=bool)[tidx[on]]
    gps = pulses.column("gps_time").to_numpy()
    order = np.argsort(gps)
    strip = np.empty(len(gps), dtype=np.int64)
    strip[order] = np.concatenate([[0], np.cumsum(np.diff(gps[order]) > STRIP_GAP_S)])
    samples, lengths = list_to_padded(pulses.column("samples"))
    amp = peak_amplitudes(samples, lengths, d["noise_mean_dn"])
    agc = pulses.column("agc").to_numpy()
    ok = on & (samples.max(axis=1) < 255)
    b, *_ = fit_b(amp[ok], agc[ok], (tidx * 100 + strip)[ok], float(np.mean(agc)))
    assert b == pytest.approx(d["b"], rel=B_TOL)


@pytest.mark.parametrize("ds", DATASETS)
def test_calibration_recovers_the_true_system_waveform(recovered, ds):
    from waveforest.sensor import load_system_waveform

    truth, out = recovered
    d = truth["datasets"][ds]
    s_true = np.array(d["system_waveform"]["s_at_a_mean"])
    t_true = np.array(d["system_waveform"]["t_ns"])
    s = load_system_waveform(out[ds][2])
    s_rec = np.interp(t_true, s.t_ns, s.s, left=0.0, right=0.0)
    err = np.linalg.norm(s_rec - s_true) / np.linalg.norm(s_true)
    assert err < S_TOL
    assert out[ds][1]["noise_mean"] == pytest.approx(d["noise_mean_dn"], abs=0.05)


CFD_TERM_TOL = 0.10
"""Tuned CFD: its width term ln(f)/delay within 10 % of the DR discriminator's (the untuned
starting pair 0.5, FWHM/2 is 34 % off the campaign's 0.35, FWHM/2)."""


@pytest.fixture(scope="module")
def vegetated(tmp_path_factory):
    """The smoke campaign's vegetation: two samples of every species per year."""
    return _campaign_through_calibrate(tmp_path_factory.mktemp("cfd"), {"samples_per_species": 2, "n_rays": 500})


@pytest.mark.parametrize("ds", DATASETS)
def test_cfd_tuning_recovers_the_dr_discriminator(vegetated, ds):
    """docs/method.md §(f): the CFD tuned on the dataset's own waveforms against its DR ranges lies on the
    ridge of the sensor's discriminator and leaves no echo-width class biased."""
    import math

    truth, out = vegetated
    dr, cal = truth["datasets"][ds]["sensor"]["dr_cfd"], out[ds][1]
    assert cal["cfd_tuning"]["tuned"], cal["cfd_tuning"]["reason"]
    term = math.log(cal["cfd"]["fraction"]) / cal["cfd"]["delay_ns"]
    assert term / (math.log(dr["fraction"]) / dr["delay_ns"]) == pytest.approx(1.0, abs=CFD_TERM_TOL)
    assert np.all(np.abs(cal["cfd_tuning"]["bias_per_width_class_m"]) < 0.01)
    assert cal["cfd_check_after"]["frac_within_0_10_m"] > 0.95  # the paper's criterion on the targets
