"""Typed settings built from the validated config, in one place.

The library below the stages takes frozen dataclasses, never the config dict; the stages call
the builders here with the config that :func:`waveforest.config.load` validated and filled
with the schema's defaults (``config.schema.yaml``, the only source of defaults). Each
builder reads its keys as ``cfg["section"]["key"]`` so that :mod:`waveforest.config_keys`
can derive from the source which keys a stage depends on.
"""

from __future__ import annotations

import copy
from dataclasses import replace
from typing import TYPE_CHECKING

from waveforest.effects import CATALOGUE
from waveforest.model.forward import MCRTSetup, SensorSettings, SensorSetup
from waveforest.sensor.calibration import calibration_effects
from waveforest.sensor.params import CFDParams, FeatureParams
from waveforest.sensor.reference import ReferenceSystem

if TYPE_CHECKING:
    from waveforest.analysis.classify import ClassifySettings
    from waveforest.analysis.compare import CompareSettings
    from waveforest.analysis.sensitivity import SensitivitySettings
    from waveforest.analysis.sensor_study import SensorStudySettings
    from waveforest.campaign.synthesize import CampaignSettings
    from waveforest.diagnose.settings import DiagnoseSettings
    from waveforest.model.agc_fit import AGCSettings
    from waveforest.model.calibration_pulses import TargetPulseSettings
    from waveforest.model.features import FeatureTableSettings
    from waveforest.model.selection import SelectRules
    from waveforest.model.self_tuning import SelfTuningSettings
    from waveforest.model.simulate import SimulateSettings
    from waveforest.report.quicklook import QuicklookSettings
    from waveforest.report.summary import ReportSettings

# -- sensor: CFD, features, the sensor model ---------------------------------------------------


def cfd_params(cfg: dict) -> CFDParams:
    """The CFD of ``sensor.cfd`` (delay and dead time None = tied to the pulse width)."""
    sec = cfg["sensor"]["cfd"]
    return CFDParams(fraction=float(sec["fraction"]), delay_ns=sec["delay_ns"], arming_sd=float(sec["arming_sd"]),
                     dead_time_ns=sec["dead_time_ns"])


def feature_params(cfg: dict) -> FeatureParams:
    """The first-echo feature settings of ``sensor.features``."""
    sec = cfg["sensor"]["features"]
    return FeatureParams(segment_sd=float(sec["segment_sd"]), peak_rise_sd=float(sec["peak_rise_sd"]),
                         echo_search_ns=float(sec["echo_search_ns"]), decomposition=bool(sec["decomposition"]))


def sensor_settings(cfg: dict) -> SensorSettings:
    """The sensor model of section ``sensor`` (record, pre-trigger, digitiser, CFD, features)."""
    s = cfg["sensor"]
    return SensorSettings(record_ns=float(s["record_ns"]), pre_trigger_m=tuple(s["pre_trigger_m"]),
                          digitizer_max=int(s["digitizer_max"]), cfd=cfd_params(cfg), features=feature_params(cfg))


def sensor_setup(cfg: dict, system, noise_mean: float, noise_sd: float, sampling_ns: float,
                 render_effects: dict | None = None, range_correction=None, cfd: CFDParams | None = None
                 ) -> SensorSetup:
    """:meth:`SensorSettings.setup` of :func:`sensor_settings` with a given S(t), noise and sampling."""
    return sensor_settings(cfg).setup(system, noise_mean, noise_sd, sampling_ns, render_effects,
                                      range_correction, cfd)


def model_sensor_effects(cfg: dict) -> dict:
    """The effects of the simulation model (``simulate.effects``) that the calibration inverts."""
    return calibration_effects(cfg["simulate"]["effects"])


def reference_system(cfg: dict) -> ReferenceSystem:
    """The studies' configured reference sensor (``sensitivity.reference_system``)."""
    ref = cfg["sensitivity"]["reference_system"]
    return ReferenceSystem(fwhm_ns=float(ref["fwhm_ns"]), plane_hdrf=float(ref["plane_hdrf"]),
                           plane_dn=float(ref["plane_dn"]), noise_mean=float(ref["noise_mean"]),
                           noise_sd=float(ref["noise_sd"]))


# -- mcrt ----------------------------------------------------------------------------------------


def mcrt_setup(cfg: dict, n_rays: int | None = None, effects: dict | None = None) -> MCRTSetup:
    """The tracer settings of section ``mcrt``; ``n_rays`` (None or 0: ``mcrt.n_rays``) and mcrt effects.

    The ray budget: a section's own ``n_rays`` fixes the rays per pulse (tolerance None); else
    ``mcrt.tolerance`` (null: ``mcrt.n_rays`` rays per pulse) with ``mcrt.min_rays`` and ``mcrt.max_rays``.
    """
    m = cfg["mcrt"]
    tol = None if n_rays else m["tolerance"]
    return MCRTSetup(n_rays=int(n_rays or m["n_rays"]), max_order=int(m["max_order"]), bin_ns=float(m["bin_ns"]),
                     viewed_diameter_m=float(m["viewed_diameter_m"]), sampler=str(m["sampler"]),
                     roulette=float(m["roulette"]), tolerance=None if tol is None else float(tol),
                     min_rays=int(m["min_rays"]), max_rays=int(m["max_rays"]), effects=dict(effects or {}))


# -- campaign ------------------------------------------------------------------------------------


def campaign_settings(cfg: dict) -> CampaignSettings:
    """The virtual campaign (``seed``, ``datasets``, ``campaign``, ``vegetation``, ``select.tree_radius_m``,
    ``mcrt.sampler``, ``mcrt.roulette``, ``mcrt.max_rays``)."""
    from waveforest.campaign.synthesize import CampaignSettings
    camp, veg = cfg["campaign"], cfg["vegetation"]
    per_species, cap, species = camp["samples_per_species"], camp["max_pulses_per_site"], camp["species"]
    return CampaignSettings(
        seed=int(cfg["seed"]), datasets=tuple(cfg["datasets"]), effects=dict(camp["effects"]),
        samples_per_species=None if per_species is None else int(per_species),
        density_scale=float(camp["density_scale"]), n_rays=int(camp["n_rays"]), max_order=int(camp["max_order"]),
        viewed_diameter_m=float(camp["viewed_diameter_m"]), disc_margin_m=float(camp["disc_margin_m"]),
        max_pulses_per_site=None if cap is None else int(cap), species=None if species is None else tuple(species),
        bvh_quality=str(camp["bvh_quality"]), ground_rho=float(veg["ground_rho"]),
        lai_jitter=float(veg["lai_jitter"]), tree_radius_m=float(cfg["select"]["tree_radius_m"]),
        sampler=str(cfg["mcrt"]["sampler"]), roulette=float(cfg["mcrt"]["roulette"]),
        tolerance=None if camp["tolerance"] is None else float(camp["tolerance"]),
        max_rays=int(cfg["mcrt"]["max_rays"]),
        record={"campaign": copy.deepcopy(dict(camp.items())),
                "vegetation": {"ground_rho": veg["ground_rho"], "lai_jitter": veg["lai_jitter"]}})


# -- select and simulate -------------------------------------------------------------------------


def select_rules(cfg: dict) -> SelectRules:
    """The selection rules (section ``select``; the compared species and heights of ``simulate``)."""
    from waveforest.model.selection import SelectRules
    sel, sim = cfg["select"], cfg["simulate"]
    return SelectRules(
        tree_radius_m=float(sel["tree_radius_m"]),
        tree_min_echo_h_m=float(sel["tree_min_echo_h_m"]),
        min_pulses=int(sel["min_pulses"]),
        comparison_species=tuple(sim["species"]),
        height_range_m={k: tuple(v) for k, v in sim["height_range_m"].items()},
    )


def simulate_settings(cfg: dict) -> SimulateSettings:
    """The simulation chain of the ``simulate`` stage (seed, ``simulate``, ``vegetation``, ``mcrt``, ``sensor``)."""
    from waveforest.model.simulate import SimulateSettings
    sim, veg = cfg["simulate"], cfg["vegetation"]
    k, cap = sim["instances_per_sample"], sim["max_pulses"]
    return SimulateSettings(
        seed=int(cfg["seed"]),
        species=tuple(sim["species"]),
        max_pulses=None if cap is None else int(cap),
        instances_per_sample=None if k is None else int(k),
        effects=dict(sim["effects"]),
        ground_rho=float(veg["ground_rho"]),
        lai_jitter=float(veg["lai_jitter"]),
        mcrt=mcrt_setup(cfg),
        sensor=sensor_settings(cfg),
    )


# -- agc -----------------------------------------------------------------------------------------


def agc_settings(cfg: dict) -> AGCSettings:
    """The fit of Eq. 1 (section ``agc``; ``calibrate.noise_tail``: n0; ``sensor.digitizer_max``: clipping)."""
    from waveforest.model.agc_fit import AGCSettings
    sec = cfg["agc"]
    fixed = sec["b"]
    return AGCSettings(statistic=str(sec["statistic"]), energy_half_window_ns=float(sec["energy_half_window_ns"]),
                       b=None if fixed is None else float(fixed), b_bounds=tuple(sec["b_bounds"]),
                       grid_points=int(sec["grid_points"]), min_pulses_per_target=int(sec["min_pulses_per_target"]),
                       pass_gap_s=float(sec["pass_gap_s"]), noise_tail=int(cfg["calibrate"]["noise_tail"]),
                       digitizer_max=float(cfg["sensor"]["digitizer_max"]))


# -- calibrate -----------------------------------------------------------------------------------


def target_pulse_settings(cfg: dict) -> TargetPulseSettings:
    """The calibration-target pulses of section ``calibrate`` (with ``sensor.digitizer_max`` and the seed)."""
    from waveforest.model.calibration_pulses import TargetPulseSettings
    sec = cfg["calibrate"]
    return TargetPulseSettings(noise_tail=int(sec["noise_tail"]), window_ns=tuple(sec["window_ns"]),
                               max_zenith_deg=float(sec["max_zenith_deg"]), cos_incidence=bool(sec["cos_incidence"]),
                               min_pulses=int(sec["min_pulses"]), digitizer_max=float(cfg["sensor"]["digitizer_max"]),
                               seed=int(cfg["seed"]))


# -- features and tune-cfd -----------------------------------------------------------------------


def feature_table_settings(cfg: dict) -> FeatureTableSettings:
    """Feature tables of pulse files (``sensor.features``; ``sensor.cfd``: the CFD, range_correction, max_echoes)."""
    from waveforest.model.features import FeatureTableSettings
    sec = cfg["sensor"]["cfd"]
    return FeatureTableSettings(features=feature_params(cfg), cfd=cfd_params(cfg),
                                range_correction=bool(sec["range_correction"]), max_echoes=int(sec["max_echoes"]))


def self_tuning_settings(cfg: dict) -> SelfTuningSettings:
    """The CFD of one pulse table tuned on its own DR echoes (section ``tune_cfd``; the range-correction
    fit of ``calibrate``; the starting CFD and the features of ``sensor``; the seed)."""
    from waveforest.model.self_tuning import SelfTuningSettings
    sec, cal = cfg["tune_cfd"], cfg["calibrate"]
    return SelfTuningSettings(seed=int(cfg["seed"]), tuning_pulses=int(sec["tuning_pulses"]),
                              noise_tail=int(sec["noise_tail"]), noise_guard_ns=float(sec["noise_guard_ns"]),
                              noise_clip_sd=float(sec["noise_clip_sd"]), min_snr=float(sec["min_snr"]),
                              tune=bool(sec["tune"]), range_correction_bins=int(cal["range_correction_bins"]),
                              range_correction_min_pulses=int(cal["range_correction_min_pulses"]),
                              cfd=cfd_params(cfg), features=feature_params(cfg))


def quicklook_settings(cfg: dict) -> QuicklookSettings:
    """The quicklook page (section ``quicklook``; the seed)."""
    from waveforest.report.quicklook import QuicklookSettings
    sec = cfg["quicklook"]
    return QuicklookSettings(seed=int(cfg["seed"]), gallery=int(sec["gallery"]), map_feature=str(sec["map_feature"]),
                             map_cells=int(sec["map_cells"]))


# -- sensitivity and sensor-study ---------------------------------------------------------------


def sensitivity_settings(cfg: dict) -> SensitivitySettings:
    """The sensitivity study (section ``sensitivity``; ``vegetation.lai_jitter``, ``mcrt``, ``sensor``, the seed)."""
    from waveforest.analysis.sensitivity import PARAMETERS, SensitivitySettings
    s = cfg["sensitivity"]
    return SensitivitySettings(
        seed=int(cfg["seed"]), pulses=int(s["pulses"]), instances=int(s["instances"]), height_m=float(s["height_m"]),
        range_m=float(s["range_m"]), xy_jitter_m=float(s["xy_jitter_m"]),
        divergence_mrad=float(s["divergence_mrad"]), sampling_ns=float(s["sampling_ns"]),
        sweeps=tuple((p, tuple(float(v) for v in s[p])) for p in PARAMETERS),
        lai_jitter=float(cfg["vegetation"]["lai_jitter"]), reference=reference_system(cfg),
        mcrt=mcrt_setup(cfg, n_rays=s["n_rays"]), sensor=sensor_settings(cfg))


def sensor_study_settings(cfg: dict) -> SensorStudySettings:
    """The sensor study (section ``sensor_study``; ``sensitivity.reference_system``, ``vegetation``,
    ``mcrt``, ``sensor``, the seed)."""
    from waveforest.analysis.sensor_study import SensorStudySettings
    s, veg = cfg["sensor_study"], cfg["vegetation"]
    return SensorStudySettings(
        seed=int(cfg["seed"]), pulses=int(s["pulses"]), instances=int(s["instances"]),
        heights_m={str(k): (float(v[0]), float(v[1])) for k, v in s["heights_m"].items()},
        range_m=float(s["range_m"]), max_scan_zenith_deg=float(s["max_scan_zenith_deg"]),
        aim_radius_m=float(s["aim_radius_m"]), min_echo_h_m={str(k): float(v) for k, v in s["min_echo_h_m"].items()},
        divergence_mrad=float(s["divergence_mrad"]), sampling_ns=float(s["sampling_ns"]),
        divergences_mrad=tuple(float(v) for v in s["divergences_mrad"]),
        pulse_widths_ns=tuple(float(v) for v in s["pulse_widths_ns"]),
        samplings_ns=tuple(float(v) for v in s["samplings_ns"]), group_size=int(s["group_size"]),
        cv_folds=int(s["cv_folds"]), ground_rho=float(veg["ground_rho"]), lai_jitter=float(veg["lai_jitter"]),
        reference=reference_system(cfg), mcrt=mcrt_setup(cfg, n_rays=s["n_rays"]), sensor=sensor_settings(cfg))


# -- compare and classify ------------------------------------------------------------------------


def compare_settings(cfg: dict) -> CompareSettings:
    """The real vs simulated comparison (``simulate.species``, ``simulate.datasets``,
    ``simulate.compare_min_h_m``; the seed)."""
    from waveforest.analysis.compare import CompareSettings
    sim = cfg["simulate"]
    return CompareSettings(species=tuple(sim["species"]), datasets=tuple(sim["datasets"]),
                           min_h_m={k: float(v) for k, v in sim["compare_min_h_m"].items()}, seed=int(cfg["seed"]))


def classify_settings(cfg: dict) -> ClassifySettings:
    """The real-data classification (section ``classify``; ``select.min_pulses``; the seed)."""
    from waveforest.analysis.classify import ClassifySettings
    c = cfg["classify"]
    return ClassifySettings(features=tuple(c["features"]),
                            extra_feature_sets=tuple(tuple(s) for s in c["extra_feature_sets"]),
                            normaliser=str(c["normaliser"]), groups=tuple(c["groups"]),
                            three_species=tuple(c["three_species"]), group_size=int(c["group_size"]),
                            cv_folds=int(c["cv_folds"]), min_pulses=int(cfg["select"]["min_pulses"]),
                            seed=int(cfg["seed"]))


# -- diagnose ------------------------------------------------------------------------------------


def diagnose_settings(cfg: dict) -> DiagnoseSettings:
    """The diagnosis (section ``diagnose``) over the study's selection, simulation chain and sensor.

    Its candidates leave out the base model's effects (``simulate.effects``); its chain traces
    ``diagnose.n_rays`` rays (at most ``mcrt.n_rays``) and ``diagnose.instances_per_sample``
    plants per field sample, with no pulse cap.
    """
    from waveforest.diagnose.power import PowerSettings
    from waveforest.diagnose.search import SearchSettings
    from waveforest.diagnose.settings import DiagnoseSettings
    from waveforest.diagnose.strata import StrataSettings
    d, p, sim = cfg["diagnose"], cfg["diagnose"]["power"], cfg["simulate"]
    base = dict(sim["effects"] or {})
    chosen = d["datasets"]
    if chosen is None:
        chosen = [ds for ds in sim["datasets"] if ds in cfg["datasets"]]
    chain = simulate_settings(cfg)
    k, near, cap, fit = d["instances_per_sample"], d["near_stem_m"], d["pulses_per_species"], d["fit_pulses"]
    ring = d["ring_m"]
    n_rays = min(d["n_rays"] or cfg["mcrt"]["n_rays"], cfg["mcrt"]["n_rays"])
    return DiagnoseSettings(
        datasets=tuple(str(ds) for ds in chosen),
        seed=int(cfg["seed"]),
        base_effects=base,
        search=SearchSettings(
            rounds=int(d["rounds"]), n_boot=int(d["bootstrap"]), values=int(d["values"]), refine=int(d["refine"]),
            replicates=int(d["pulses_per_value"]), alpha=float(d["alpha"]),
            min_relative_reduction=float(d["min_relative_reduction"]),
            candidates=tuple(c for c in (d["candidates"] or CATALOGUE) if c not in base),
            refit=bool(d["refit"]), crossfit=bool(d["crossfit"]), features=tuple(d["features"]),
            signature_alpha=None if d["signature_alpha"] is None else float(d["signature_alpha"]),
            min_pulses=int(d["min_cell_pulses"]), min_samples=int(d["min_cell_samples"])),
        power=PowerSettings(replicates=int(p["replicates"]), values=int(p["values"]), power=float(p["power"]),
                            pool=int(p["pool"])),
        strata=StrataSettings(
            rules=select_rules(cfg), compare_min_h_m={str(s): float(h) for s, h in sim["compare_min_h_m"].items()},
            near_stem_m=None if near is None else float(near), below_crown=bool(d["below_crown"]),
            pulses_per_species=None if cap is None else int(cap), seed=int(cfg["seed"]),
            sensor=sensor_settings(cfg), ring_m=None if ring is None else float(ring)),
        simulate=replace(chain, max_pulses=None, instances_per_sample=None if k is None else int(k),
                         mcrt=replace(chain.mcrt, n_rays=int(n_rays),
                                      tolerance=None if d["n_rays"] else chain.mcrt.tolerance)),
        range_correction=bool(cfg["sensor"]["cfd"]["range_correction"]),
        fit_pulses=None if fit is None else int(fit),
    )


# -- report --------------------------------------------------------------------------------------


def report_settings(cfg: dict) -> ReportSettings:
    """What the report states of the run: data source, seed, datasets, the settings its sentences
    name."""
    from waveforest.report.summary import ReportSettings
    sim, sens, cls = cfg["simulate"], cfg["sensitivity"], cfg["classify"]
    return ReportSettings(
        datasets=tuple(str(x) for x in cfg["datasets"]),
        sensor_study_range_m=float(cfg["sensor_study"]["range_m"]),
        seed=int(cfg["seed"]), data=None if cfg["data"] is None else str(cfg["data"]),
        campaign_effects=tuple((str(k), float(v)) for k, v in cfg["campaign"]["effects"].items()),
        compare_datasets=tuple(str(x) for x in sim["datasets"]), compare_species=tuple(sim["species"]),
        compare_height_range_m=tuple((str(k), (float(v[0]), float(v[1]))) for k, v in sim["height_range_m"].items()),
        compare_min_h_m=tuple((str(k), float(v)) for k, v in sim["compare_min_h_m"].items()),
        select_min_pulses=int(cfg["select"]["min_pulses"]),
        sensitivity_height_m=float(sens["height_m"]), sensitivity_range_m=float(sens["range_m"]),
        sensitivity_xy_jitter_m=float(sens["xy_jitter_m"]),
        sensor_study_species=tuple(str(k) for k in cfg["sensor_study"]["heights_m"]),
        classify_features=tuple(cls["features"]),
        classify_groups=tuple(cls["groups"]), classify_normaliser=str(cls["normaliser"]))
