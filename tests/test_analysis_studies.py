"""sensitivity and sensor_study on analytic plate scenes: Eq. 7 amplitudes, energy conservation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
from fixtures.tables import plate_scene

from waveforest import config
from waveforest.analysis import sensitivity as sensitivity_lib
from waveforest.analysis import sensor_study as sensor_study_lib
from waveforest.cli import main
from waveforest.sensor import gaussian_system_waveform
from waveforest.sensor.reference import reference_sensor
from waveforest.settings import reference_system, sensitivity_settings, sensor_study_settings
from waveforest.stages import sensitivity, sensor_study

RHO = {"birch": 0.20, "raspberry": 0.30, "fireweed": 0.25}
"""Plate reflectances: low enough that the narrowest pulse is not clipped at 255 DN, high enough
that the widest one loses little energy below the segment threshold (3 noise SDs)."""


def species_plates(species, height, seed, **kw):
    """Plates whose reflectance identifies the species (a separable toy 'vegetation')."""
    kw.setdefault("leaf_rho", RHO[species])
    return plate_scene(species, height, seed, **kw)


def _cfg(**over):
    base = {"seed": 11, "mcrt": {"n_rays": 100, "max_order": 2},
            "sensitivity": {"pulses": 12, "instances": 3, "mean_leaf_angle_deg": [], "leaf_tau": [],
                            "leaf_rho": [0.30, 0.50], "leaf_area_scale": [1.0]},
            "sensor_study": {"pulses": 20, "instances": 4, "divergences_mrad": [0.15, 0.3],
                             "pulse_widths_ns": [5.0, 7.2, 10.0], "samplings_ns": [0.5, 1.0, 2.0], "cv_folds": 3,
                             "max_scan_zenith_deg": 5.0}}  # amplitude ~ rho cos^3: keep the species apart
    base.update(over)
    return config.load(overrides=base)


def test_study_settings_have_no_defaults_and_follow_the_config():
    cfg = _cfg()
    st, ss = sensitivity_settings(cfg), sensor_study_settings(cfg)
    for obj in (st, ss):
        assert all(f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
                   for f in dataclasses.fields(obj))
    assert [(p, v) for p, v, _ in sensitivity_lib.sweep(st)][1:] == [
        ("leaf_rho", 0.3), ("leaf_rho", 0.5), ("leaf_area_scale", 1.0)]
    assert st.mcrt.n_rays == 100 and st.reference == ss.reference == reference_system(cfg)
    assert list(ss.heights_m) == ["birch", "raspberry", "fireweed"] and sensor_study_lib.instances_of(ss) == 4
    assert sensor_study_lib.divergences(ss) == [0.15, 0.3] and len(sensor_study_lib.sweep(ss)) == 2 + 3 + 3


def test_reference_sensor_scale():
    cfg = _cfg()
    ref = reference_sensor(reference_system(cfg), None, None, 1200.0)
    r = cfg["sensitivity"]["reference_system"]
    # a spike of sigma = HDRF / pi at R peaks at plane_dn (Eq. 7)
    assert ref.system.peak * r["plane_hdrf"] / np.pi / 1200.0**2 == pytest.approx(r["plane_dn"], rel=1e-9)
    assert ref.system.fwhm_ns == pytest.approx(7.2, rel=1e-3)
    with pytest.raises(ValueError, match="no such file"):
        reference_sensor(reference_system(cfg), "/nonexistent/s.parquet")


def test_sensitivity_apeak_is_linear_in_rho(tmp_path):
    cfg = _cfg()
    out = sensitivity.run(tmp_path, cfg, progress=False, scene_builder=plate_scene)
    t = pd.read_csv(out.table).set_index(["parameter", "value"])
    a3, a5 = t.loc[("leaf_rho", 0.3), "mean_apeak"], t.loc[("leaf_rho", 0.5), "mean_apeak"]
    plane_dn = cfg["sensitivity"]["reference_system"]["plane_dn"]
    # Eq. 7: Apeak = plane_dn * rho / 0.34; 1-ns sampling of a 7.2-ns pulse loses < 1.5 %
    assert a5 / a3 == pytest.approx(0.5 / 0.3, rel=0.02)
    assert a5 == pytest.approx(plane_dn * 0.5 / 0.34, rel=0.03)
    row = t.loc[("leaf_rho", 0.5)]
    assert row["n_echo"] == 12 and row["se_apeak"] == pytest.approx(row["sd_apeak"] / np.sqrt(12), rel=1e-5)
    assert t.loc[("leaf_rho", 0.5), "mean_H"] == pytest.approx(3.0, abs=0.03)  # the plate top, no ground
    assert len(t) == 2 + 1 and out.figure.stat().st_size > 5000
    assert not t.reset_index().select_dtypes("number").isna().any().any()  # no NaN (smoke check)
    base = pd.read_csv(tmp_path / "sensitivity_baseline.csv")
    assert len(base) == 1 and base.loc[0, "mean_apeak"] == pytest.approx(plane_dn * 0.47 / 0.34, rel=0.03)
    # same seed -> same table, whatever the worker threads
    again = sensitivity.run(tmp_path / "b", cfg, progress=False, scene_builder=plate_scene, threads=1)
    assert pd.read_csv(again.table).equals(pd.read_csv(out.table))
    pulses = pd.read_parquet(out.pulses_table)
    assert pd.read_parquet(again.pulses_table).equals(pulses) and pulses["instance"].nunique() == 3


def test_sensor_study_is_separable_and_conserves_energy(tmp_path):
    cfg = _cfg()
    out = sensor_study.run(tmp_path, cfg, progress=False, scene_builder=species_plates)
    t = pd.read_csv(out.table)
    n_settings = 2 + 3 + 3
    assert len(t) == n_settings * 2 * 2 and out.n_settings == n_settings
    assert set(t["level"]) == {"1-pulse", "5-pulse"} and set(t["scheme"]) == {"resubstitution", "cross_validated"}
    assert (t["accuracy"] == 1.0).all()  # the plates differ in reflectance: perfectly separable
    assert not t.select_dtypes("number").isna().any().any()
    f = pd.read_csv(out.features_table)
    for param in ("pulse_width_ns", "sampling_ns"):
        e = f[f.parameter == param].pivot(index="value", columns="species", values="mean_E")
        # E = sum (V - c) dt: the pulse energy, the same at every width (constant energy) and sampling
        assert np.allclose(e / e.iloc[0], 1.0, atol=0.04), e
    apk = f[f.parameter == "pulse_width_ns"].pivot(index="value", columns="species", values="mean_Apeak")
    assert (apk.loc[5.0] > 1.6 * apk.loc[10.0]).all()  # half the width, about twice the peak
    fw = f[f.parameter == "pulse_width_ns"].pivot(index="value", columns="species", values="mean_FWHM")
    assert fw.loc[10.0].to_numpy() == pytest.approx(10.0, rel=0.05)
    serial = sensor_study.run(tmp_path / "serial", cfg, progress=False, scene_builder=species_plates, threads=1)
    assert pd.read_csv(serial.features_table).equals(f)  # worker threads do not change the result


def test_cli_with_a_calibrated_system(tmp_path):
    """--system/--calibration are read; the vegetation model is needed for the real command."""
    vegetation = pytest.importorskip("waveforest.vegetation", reason="vegetation module not available")
    if not hasattr(vegetation, "build_scene"):
        pytest.skip("waveforest.vegetation.build_scene not available yet")
    sw = gaussian_system_waveform(7.2, 5e8)
    sw.save(tmp_path / "s.parquet")
    (tmp_path / "s.json").write_text('{"dataset": "2010_12_1", "noise_mean": 9.0, "noise_sd": 1.2}')
    cfgp = tmp_path / "c.yaml"
    cfgp.write_text("mcrt: {n_rays: 50, max_order: 2}\nsensitivity: {pulses: 4, instances: 2, mean_leaf_angle_deg: [],"
                    " leaf_tau: [], leaf_rho: [0.47], leaf_area_scale: []}\n")
    main(["sensitivity", "--system", str(tmp_path / "s.parquet"), "--out", str(tmp_path / "o"), "--config", str(cfgp)])
    t = pd.read_csv(tmp_path / "o" / "sensitivity.csv")
    assert list(t["parameter"]) == ["leaf_rho"] and t.loc[0, "n_pulses"] == 4
