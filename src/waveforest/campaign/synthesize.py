"""Generate the virtual ALS60 campaign: ``run(settings, out_dir, effects)``.

Order of work (each step's randomness has its own keyed stream, :func:`waveforest.rng.stream_generator`):

1. parameters (``resources/campaign``) and the config's datasets; the true sensor of each
   dataset (:class:`.truth_sensor.TruthSensor`);
2. the layout of stands, field samples and targets (:func:`.layout.build_layout`);
3. per dataset: strips and the pulses near its year's sites (:mod:`.flight`);
4. per site (progress bar; :mod:`.site_trace`, ``--threads`` sites at a time): its one true
   scene (:mod:`.scenes`), every pulse of every dataset over it traced in one batched
   :func:`waveforest.mcrt.trace` call; the noise-free peak of each pulse at unit gain (for
   the AGC loop) and sigma(t) kept (trimmed, float32). The result does not depend on the
   thread count;
5. per dataset: the AGC loop over its pulses in time order (:mod:`.agc_loop`), the sensor
   records each pulse (:func:`.truth_sensor.record`), the recorded geometry gets the per-strip
   positioning errors and the ``xy_error`` effect, and the pulse table goes to a LAS 1.4 file
   (point format 9, 8-bit samples, waveform packets inside the file: EVLR 65535) through
   :func:`waveforest.io.las.write.write_waveform_las`, with its trajectory CSV;
6. ``datasets.csv``, ``fields.csv``, ``targets.csv``, ``README.md``, ``truth.json`` and
   ``truth_pulses.parquet``.

The folder is built beside ``out_dir`` and renamed onto it at the end: a failure leaves
``out_dir`` as it was.

Hidden effects (src/waveforest/effects.py) act where their physics does: ``understory``,
``clumping``, ``lad_shift``, ``leaf_albedo`` in the vegetation instances; ``specular``,
``hotspot`` in the MCRT; ``noise_autocorr``, ``nonlinearity``, ``trigger_loss`` in the
sensor; ``xy_error`` in the recorded geometry: the recorded trajectory and the recorded points
drift together horizontally by a Gauss-Markov error of SD xy_error per axis and correlation
time ``flight.georef_tau_s`` (:func:`.flight.georeferencing_error`), so a recorded beam is the
true one moved as a whole; the field samples stay where the plants are.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np
import pandas as pd
import pyarrow as pa

from waveforest import __version__
from waveforest.atomic import OutputFolder, plain
from waveforest.campaign.agc_loop import agc_sequence
from waveforest.campaign.flight import georeferencing_error, plan_flight, site_pulses
from waveforest.campaign.layout import FIELD_COLUMNS, TARGET_COLUMNS, build_layout
from waveforest.campaign.params import CAMPAIGN_RESOURCES, coverage, load_datasets, load_layout
from waveforest.campaign.readme import readme_text
from waveforest.campaign.site_trace import SiteJob, TraceSettings, trace_sites
from waveforest.campaign.truth_sensor import MAX_ECHOES, TruthSensor, record
from waveforest.constants import RANGE_PER_NS
from waveforest.effects import CATALOGUE, active, parse_effects
from waveforest.errors import WaveforestError
from waveforest.io.las.write import write_waveform_las
from waveforest.io.pulses import PULSE_SCHEMA, padded_to_list, write_table
from waveforest.rng import stream_generator
from waveforest.vegetation import species_table
from waveforest.workers import unordered_map

VEGETATION_EFFECTS = ("understory", "clumping", "lad_shift", "leaf_albedo")
MCRT_EFFECTS = ("specular", "hotspot")
SENSOR_EFFECTS = ("noise_autocorr", "nonlinearity", "trigger_loss")

DIGITIZER_GAIN, DIGITIZER_OFFSET = 1.0, 0.0
"""Waveform packet descriptor: volts per DN and volts at DN 0 (the ALS60's are not published)."""

EFFECT_LIMITS = {
    "understory": (0.0, np.inf, "[0, inf)"), "clumping": (0.0, np.inf, "[0, inf)"),
    "xy_error": (0.0, np.inf, "[0, inf)"), "specular": (0.0, 1.0, "[0, 1]"),
    "hotspot": (1e-9, np.inf, "(0, inf)"), "lad_shift": (-90.0, 90.0, "[-90, 90]"),
    "leaf_albedo": (1e-9, np.inf, "(0, inf)"), "noise_autocorr": (-0.999999, 0.999999, "(-1, 1)"),
    "nonlinearity": (0.0, np.inf, "[0, inf)"), "trigger_loss": (0.0, 0.999999, "[0, 1)"),
}
"""Physically meaningful range of each effect's value."""


class SynthesizeError(WaveforestError):
    """The campaign cannot be generated as configured."""


@dataclass(frozen=True)
class CampaignSettings:
    """The virtual campaign as configured (built by :func:`waveforest.settings.campaign_settings`).

    Attributes
    ----------
    seed : int
        Master seed.
    datasets : tuple of str
        Datasets to generate (names of ``resources/campaign/datasets.csv``).
    effects : dict
        Hidden effects of config ``campaign.effects``, name -> value.
    samples_per_species, density_scale, n_rays, max_order, viewed_diameter_m, disc_margin_m,
    max_pulses_per_site, species, bvh_quality
        Config section ``campaign`` (``species`` None = every species of Table 1).
    ground_rho, lai_jitter : float
        Config section ``vegetation``.
    tree_radius_m : float
        Config ``select.tree_radius_m``, m.
    sampler, roulette
        The MCRT estimator (config ``mcrt.sampler``, ``mcrt.roulette``: the model's).
    tolerance, max_rays
        The adaptive ray budget of the field samples (config ``campaign.tolerance``, ``mcrt.max_rays``).
    record : dict
        The config sections as ``truth.json`` records them (``campaign``, ``vegetation``); written, not read.
    """

    seed: int
    datasets: tuple[str, ...]
    effects: dict
    samples_per_species: int | None
    density_scale: float
    n_rays: int
    max_order: int
    viewed_diameter_m: float
    disc_margin_m: float
    max_pulses_per_site: int | None
    species: tuple[str, ...] | None
    bvh_quality: str
    ground_rho: float
    lai_jitter: float
    tree_radius_m: float
    sampler: str
    roulette: float
    tolerance: float | None
    max_rays: int
    record: dict


@dataclass
class CampaignSummary:
    """What :func:`run` wrote."""

    out_dir: Path
    pulses: dict[str, int] = field(default_factory=dict)
    points: dict[str, int] = field(default_factory=dict)
    n_fields: int = 0
    n_targets: int = 0
    effects: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)

    def line(self) -> str:
        """One-line summary for the CLI."""
        eff = ", ".join(f"{k}={v:g}" for k, v in active(self.effects).items()) or "none"
        return (f"wrote {self.out_dir}: {len(self.pulses)} datasets, {sum(self.pulses.values()):,} pulses "
                f"({sum(self.points.values()):,} LAS points), {self.n_fields} field samples, "
                f"{self.n_targets} targets; hidden effects: {eff}; {self.seconds:.0f} s")


def resolve_effects(configured, effects=None) -> dict[str, float]:
    """All ten effects with their values: off values, then ``configured`` (config
    ``campaign.effects``), then ``effects`` (each a mapping or "NAME=VALUE" strings)."""
    values = {name: e.off for name, e in CATALOGUE.items()}
    values.update(parse_effects(configured))
    values.update(parse_effects(effects))
    for name, v in values.items():
        lo, hi, text = EFFECT_LIMITS[name]
        if not (np.isfinite(v) and lo <= v <= hi):
            raise SynthesizeError(f"effect {name} = {v!r}: expected a value in {text}")
    return values


def _sites_table(fields: pd.DataFrame, targets: pd.DataFrame, year: int, margin: float, tree_radius: float) -> pd.DataFrame:
    f = fields[fields["year"] == year]
    t = targets[targets["year"] == year]
    fr = np.where(f["is_tree"] == 1, tree_radius, f["radius_m"]) + margin
    return pd.concat([
        pd.DataFrame({"site": f["sample_id"].to_numpy(), "s": f["s"].to_numpy(), "w": f["w"].to_numpy(),
                      "ground_z": f["ground_z"].to_numpy(), "disc_m": fr}),
        pd.DataFrame({"site": t["target_id"].to_numpy(), "s": t["s"].to_numpy(), "w": t["w"].to_numpy(),
                      "ground_z": t["z"].to_numpy(), "disc_m": t["radius_m"].to_numpy() + margin}),
    ], ignore_index=True)


def _crs_wkt() -> str | None:
    path = CAMPAIGN_RESOURCES / "crs.wkt"
    return path.read_text().strip() if path.exists() else None


@dataclass
class _Sites:
    """The planned campaign: datasets, their true sensors, the layout, its sites and the pulses."""

    datasets: pd.DataFrame
    sensors: dict
    lay: dict
    layout: object
    fields: pd.DataFrame
    targets: pd.DataFrame
    plans: dict
    pulses: dict
    allp: pd.DataFrame
    site_info: pd.DataFrame


def run(settings: CampaignSettings, out_dir: str | os.PathLike, effects=None, *,
        progress: bool = True, force: bool = False) -> CampaignSummary:
    """Generate the virtual campaign into ``out_dir`` (module docstring).

    Parameters
    ----------
    settings : CampaignSettings
    out_dir : path
        Campaign folder to write, whole or not at all (:class:`waveforest.atomic.OutputFolder`:
        an existing folder is replaced only if synthesize wrote all it holds).
    effects : mapping or list of "NAME=VALUE", optional
        Hidden effects on top of ``settings.effects``.
    progress : bool
        Progress bars on stderr.
    force : bool
        Replace ``out_dir`` even if it holds files synthesize did not write.

    Returns
    -------
    CampaignSummary
    """
    t_start = time.perf_counter()
    out = Path(out_dir)
    eff = resolve_effects(settings.effects, effects)
    folder = OutputFolder(out, "synthesize", force=force)  # before the minutes of generation, not after
    sites = _plan_sites(settings)
    timings = {"plan": time.perf_counter() - t_start, "sites_wall": 0.0, "scenes": 0.0, "trace": 0.0,
               "record_write": 0.0}
    # 4. trace every site once
    a0, batches, cover_true = _trace_sites(sites.allp, sites.site_info, sites.datasets, sites.sensors, settings,
                                           eff, timings, progress)
    t_rec = time.perf_counter()
    sites.fields["canopy_cover_pct"] = sites.fields["sample_id"].map(
        _canopy_cover(sites.layout, cover_true, sites.lay, settings.seed)).to_numpy()
    # 5. and 6. in a folder beside out, renamed onto it at the end
    summary = CampaignSummary(out_dir=out, effects=eff, timings=timings)
    with folder as tmp:
        _write_campaign(tmp, settings, sites, eff, a0, batches, cover_true, summary)
    timings["record_write"] = time.perf_counter() - t_rec
    summary.seconds = time.perf_counter() - t_start
    return summary


def _plan_sites(settings: CampaignSettings) -> _Sites:
    """Steps 1-3: the datasets and their true sensors, the layout, and the pulses near its sites."""
    datasets = load_datasets(list(settings.datasets))
    if datasets.empty:
        raise SynthesizeError("config datasets: no dataset to generate")
    sensors = {row["dataset"]: TruthSensor.from_row(row) for _, row in datasets.iterrows()}
    lay = load_layout()
    per_species = settings.samples_per_species
    layout = build_layout(species_table(), None if per_species is None else int(per_species), settings.seed)
    fields, targets = campaign_sites(layout, sorted(set(int(y) for y in datasets["year"])), settings.species)
    plans, pulses = plan_pulses(datasets, fields, targets, layout, lay, settings)
    allp = pd.concat(pulses.values(), ignore_index=True)
    if allp.empty:
        raise SynthesizeError("no pulse reaches any site (check density_scale and the layout)")
    allp["row"] = np.concatenate([np.arange(len(p)) for p in pulses.values()])
    site_info = _site_info(fields, targets, float(settings.disc_margin_m))
    for p in pulses.values():
        p["kind"] = p["site"].map(site_info["kind"]).to_numpy()
    return _Sites(datasets, sensors, lay, layout, fields, targets, plans, pulses, allp, site_info)


def _write_campaign(tmp: Path, settings: CampaignSettings, sites: _Sites, eff: dict, a0: dict, batches: dict,
                    cover_true: dict, summary: CampaignSummary) -> None:
    """Steps 5 and 6 into the folder ``tmp``: per dataset its LAS file and trajectory (datasets
    shared over worker threads), then the tables, ``truth_pulses.parquet``, ``truth.json`` and
    the README; fills ``summary``."""
    seed = settings.seed
    truth_ds, truth_rows = {}, []
    wkt = _crs_wkt()

    def record(row):
        ds = row["dataset"]
        _, info_ds, rows_ds = record_dataset(row, sites.sensors[ds], sites.plans[ds], sites.pulses[ds], a0[ds],
                                             batches[ds], eff, seed, sites.lay, tmp, wkt)
        batches[ds] = None  # free sigma
        return ds, info_ds, rows_ds

    rows = [row for _, row in sites.datasets.iterrows()]  # datasets share the worker threads
    done = dict(unordered_map(record, rows, max(1, int(numba.get_num_threads()))))
    for i in range(len(rows)):  # dataset order, whatever order the workers finished in
        ds, info_ds, rows_ds = done[i]
        truth_ds[ds] = info_ds
        truth_rows.append(rows_ds)
        summary.pulses[ds] = info_ds["n_pulses"]
        summary.points[ds] = info_ds["n_points"]
    _write_tables(tmp, sites.datasets, sites.fields, sites.targets, float(settings.density_scale))
    write_table(pa.Table.from_pandas(pd.concat(truth_rows, ignore_index=True), preserve_index=False),
                tmp / "truth_pulses.parquet")
    manifest = _truth_manifest(settings, eff, sites.datasets, sites.layout, sites.targets, truth_ds, cover_true)
    with open(tmp / "truth.json", "w") as fh:
        json.dump(plain(manifest), fh, indent=1, sort_keys=False)
    (tmp / "README.md").write_text(readme_text())
    summary.n_fields, summary.n_targets = len(sites.fields), len(sites.targets)


def campaign_sites(layout, years: list[int], only) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The field samples and targets of ``years`` (samples only of the species ``only``, if given).

    Raises SynthesizeError for a species of ``only`` the layout does not have.
    """
    fields = layout.fields[layout.fields["year"].isin(years)].reset_index(drop=True)
    targets = layout.targets[layout.targets["year"].isin(years)].reset_index(drop=True)
    if only:
        unknown = sorted(set(only) - set(layout.fields["species"]))
        if unknown:
            raise SynthesizeError(f"campaign.species: unknown species {', '.join(unknown)}")
        fields = fields[fields["species"].isin(only)].reset_index(drop=True)
    return fields, targets


def plan_pulses(datasets: pd.DataFrame, fields: pd.DataFrame, targets: pd.DataFrame, layout, lay: dict,
                settings: CampaignSettings) -> tuple[dict, dict]:
    """Per dataset, its flight plan (:func:`.flight.plan_flight`) and the pulses near its year's
    sites (:func:`.flight.site_pulses`, with columns ``dataset`` first and ``year``). With Table 1's
    design counts a field sample is recorded with its ``coverage.csv`` coverage; targets always."""
    seed, margin = settings.seed, float(settings.disc_margin_m)
    tree_r = float(settings.tree_radius_m)
    cap = settings.max_pulses_per_site
    design = settings.samples_per_species is None
    species_of = fields.set_index("sample_id")["species"]
    plans, pulses = {}, {}
    for _, row in datasets.iterrows():
        ds, year = row["dataset"], int(row["year"])
        sites = _sites_table(fields, targets, year, margin, tree_r)
        if design:  # coverage.csv is fitted to Table 1's design counts
            species = sites["site"].map(species_of).to_numpy(object)
            sites["coverage"] = np.where(pd.isna(species), 1.0, coverage(ds, species))
        plans[ds] = plan_flight(row, layout.frame, lay, float(settings.density_scale), seed,
                                float(sites["ground_z"].mean()))
        p = site_pulses(plans[ds], sites, lay, seed, None if cap is None else int(cap))
        p.insert(0, "dataset", ds)
        p["year"] = year
        pulses[ds] = p
    return plans, pulses


def _canopy_cover(layout, cover_true: dict, lay: dict, seed: int) -> pd.Series:
    """The visually estimated canopy cover of the marked samples, %, by sample_id (NaN elsewhere).

    The true cover (fraction) x 100 plus N(0, ``canopy_cover_sd_pct``), rounded to
    ``canopy_cover_step_pct`` and clipped to [0, 100]; stream ("cover",) over all samples of the layout.
    """
    smp = lay["samples"]
    crng = stream_generator(seed, "cover")
    noise = crng.normal(0.0, float(smp["canopy_cover_sd_pct"]), len(layout.fields))
    est = layout.fields["sample_id"].map(cover_true).to_numpy(dtype=float) * 100.0 + noise
    step = float(smp["canopy_cover_step_pct"])
    est = np.clip(np.round(est / step) * step, 0.0, 100.0)
    return pd.Series(np.where(layout.fields["cover_estimated"].to_numpy(), est, np.nan),
                     index=layout.fields["sample_id"])


def _truth_manifest(settings: CampaignSettings, eff: dict, datasets: pd.DataFrame, layout, targets: pd.DataFrame,
                    truth_ds: dict, cover_true: dict) -> dict:
    """The content of ``truth.json``: seed, effects, config, frame, per-dataset truth, targets, true cover."""
    return {
        "description": "Truth of the virtual ALS60 campaign. No analysis step reads this file.",
        "waveforest_version": __version__,
        "seed": settings.seed,
        "effects": eff,
        "active_effects": active(eff),
        "config": {"datasets": list(datasets["dataset"]), **settings.record},
        "frame": {"origin_x": layout.frame.origin_x, "origin_y": layout.frame.origin_y,
                  "azimuth_deg": layout.frame.azimuth_deg},
        "datasets": truth_ds,
        "targets": {r["target_id"]: {"true_rho": r["true_rho"], "side_m": r["side_m"],
                                     "on_ground_rho": None if pd.isna(r["on_ground_rho"]) else float(r["on_ground_rho"])}
                    for _, r in targets.iterrows()},
        "canopy_cover_true_pct": {k: 100.0 * v for k, v in cover_true.items()},
    }


def _site_info(fields: pd.DataFrame, targets: pd.DataFrame, margin: float) -> pd.DataFrame:
    """One row per site (sample or target), indexed by site id: what its true scene needs."""
    return pd.concat([
        pd.DataFrame({"site": fields["sample_id"], "kind": "sample", "x": fields["x"], "y": fields["y"],
                      "z": fields["ground_z"], "species": fields["species"], "height_m": fields["height_m"],
                      "rho": np.nan, "side_m": np.nan, "on_ground_rho": np.nan, "disc_m": 0.0}),
        pd.DataFrame({"site": targets["target_id"], "kind": "target", "x": targets["x"], "y": targets["y"],
                      "z": targets["z"], "species": "", "height_m": 0.0, "rho": targets["true_rho"],
                      "side_m": targets["side_m"], "on_ground_rho": pd.to_numeric(targets["on_ground_rho"]),
                      "disc_m": targets["radius_m"] + margin}),
    ], ignore_index=True).set_index("site")


def _trace_sites(allp: pd.DataFrame, site_info: pd.DataFrame, datasets: pd.DataFrame, sensors: dict,
                 settings: CampaignSettings, eff: dict, timings: dict, progress: bool):
    """Build each site's true scene once and trace all its pulses of all datasets in one call
    (:mod:`.site_trace`; the sites are shared over Numba's thread count of worker threads).

    Returns the unit-gain analog peak of every pulse (per dataset, by row), the trimmed
    sigma(t) batches per dataset ``(site, rows, sigma, t0_ns, range_m)`` in site order and
    the true cover (share of first hits on vegetation) of every traced sample.
    """

    names = list(datasets["dataset"])
    groups = allp.groupby("site", sort=False).indices
    sites = [s for s in site_info.index if s in groups]
    jobs = _site_jobs(allp, site_info.loc[sites], groups, datasets)
    t0 = time.perf_counter()
    results = trace_sites(jobs, _site_trace_settings(settings, eff, tuple(sensors[ds] for ds in names)),
                          workers=max(1, int(numba.get_num_threads())), progress=progress)
    timings["sites_wall"] = time.perf_counter() - t0
    timings["scenes"] = sum(r.scene_s for r in results.values())
    timings["trace"] = sum(r.trace_s for r in results.values())

    a0 = {ds: np.zeros(int(np.sum(allp["dataset"] == ds))) for ds in names}
    batches = {ds: [] for ds in names}
    cover_true = {}
    for site in sites:  # site order, whatever order the workers finished in
        r = results[site]
        if r.cover is not None:
            cover_true[site] = r.cover
        for i, part in sorted(r.parts.items()):
            ds = names[i]
            a0[ds][part.rows] = part.a0_dn
            batches[ds].append((site, part.rows, part.sigma, part.t0_ns, part.range_m))
    return a0, batches, cover_true


def _site_trace_settings(settings: CampaignSettings, eff: dict, sensors: tuple) -> TraceSettings:
    """What every site's tracing shares: the campaign's MCRT and vegetation settings, its true
    effects and the true sensor of each dataset (by dataset index)."""
    return TraceSettings(
        seed=settings.seed, n_rays=int(settings.n_rays), max_order=int(settings.max_order),
        viewed_diameter_m=float(settings.viewed_diameter_m), specular=float(eff["specular"]),
        hotspot=float(eff["hotspot"]), trigger_loss=float(eff["trigger_loss"]),
        ground_rho=float(settings.ground_rho), lai_jitter=float(settings.lai_jitter),
        vegetation_effects=tuple((k, float(eff[k])) for k in VEGETATION_EFFECTS),
        sensors=sensors, bvh_quality=str(settings.bvh_quality),
        sampler=str(settings.sampler), roulette=float(settings.roulette), tolerance=settings.tolerance,
        max_rays=int(settings.max_rays))


def _site_jobs(allp: pd.DataFrame, si: pd.DataFrame, groups: dict, datasets: pd.DataFrame) -> list[SiteJob]:
    """One :class:`.site_trace.SiteJob` per site of ``si`` (rows of :func:`_site_info`), its pulses
    the rows ``groups[site]`` of ``allp`` in scene-local coordinates."""
    ds_index = {ds: i for i, ds in enumerate(datasets["dataset"])}
    divergence = datasets.set_index("dataset")["divergence_mrad"]
    # per-pulse and per-site arrays once: a site's job is then slices (no pandas per site)
    sensor = allp[["sensor_x", "sensor_y", "sensor_z"]].to_numpy(np.float64)
    direction = allp[["dir_x", "dir_y", "dir_z"]].to_numpy(np.float64)
    div = allp["dataset"].map(divergence).to_numpy(np.float64)
    ds_of = allp["dataset"].map(ds_index).to_numpy(np.int64)
    range_m = allp["range_ground_m"].to_numpy(np.float64)
    row = allp["row"].to_numpy(np.int64)
    xyz = si[["x", "y", "z"]].to_numpy(np.float64)
    num = {c: si[c].to_numpy(np.float64) for c in ("height_m", "rho", "side_m", "on_ground_rho", "disc_m")}
    kind, species = si["kind"].astype(str).to_numpy(), si["species"].astype(str).to_numpy()
    jobs = []
    for k, site in enumerate(si.index):
        idx = groups[site]
        jobs.append(SiteJob(
            site=site, kind=kind[k], species=species[k], height_m=float(num["height_m"][k]),
            rho=float(num["rho"][k]), side_m=float(num["side_m"][k]),
            on_ground_rho=float(num["on_ground_rho"][k]), reach_m=float(num["disc_m"][k]) + 1.0,
            origin=sensor[idx] - xyz[k], direction=direction[idx], divergence_mrad=div[idx],
            range_m=range_m[idx], dataset=ds_of[idx], rows=row[idx]))
    return jobs


def record_dataset(row, sensor: TruthSensor, plan, p: pd.DataFrame, a0: np.ndarray, batches, eff, seed,
                    lay, out: Path, wkt):
    """Run the AGC loop and the sensor over one dataset's pulses; write its LAS and trajectory."""

    ds = row["dataset"]
    n = len(p)
    agc, gain, observed = agc_sequence(p["gps_time"].to_numpy(), a0, p["strip"].to_numpy(), sensor.agc,
                                       stream_generator(seed, "agc", ds), saturation_dn=eff["nonlinearity"])
    n_s = sensor.n_samples
    samples, first, echo_ns, echo_amp, inten, n_echo, walk = _record_sites(sensor, batches, gain, n, eff, seed, ds)

    # geometry: true positions, then the recording errors
    srng = stream_generator(seed, "strip_error", ds)
    n_strips = len(plan.strips)
    strip_off = np.column_stack([srng.normal(0, sensor.strip_xy_sd_m, (n_strips, 2)),
                                 srng.normal(0, sensor.strip_z_sd_m, n_strips)])
    traj = plan.trajectory(float(lay["flight"]["trajectory_hz"]))
    traj_xy, xy = georeferencing_error(traj, p["strip"].to_numpy(), p["gps_time"].to_numpy(), eff["xy_error"],
                                       float(lay["flight"]["georef_tau_s"]), stream_generator(seed, "xy_error", ds))
    sensor_true = p[["sensor_x", "sensor_y", "sensor_z"]].to_numpy()
    d = p[["dir_x", "dir_y", "dir_z"]].to_numpy()
    shift = strip_off[p["strip"].to_numpy()] + np.column_stack([xy, np.zeros(n)])
    anchor = sensor_true + d * (first * RANGE_PER_NS)[:, None] + shift
    echo_xyz = sensor_true[:, None, :] + d[:, None, :] * (echo_ns * RANGE_PER_NS)[:, :, None] + shift[:, None, :]
    sensor_rec = sensor_true + shift
    keep = n_echo > 0
    kept = np.flatnonzero(keep)
    lengths = n_echo[kept]
    k = len(kept)
    echo_t = echo_ns - first[:, None]

    def lst(a, typ):
        return padded_to_list(np.nan_to_num(a[kept]), lengths, typ)

    table = pa.Table.from_arrays([
        pa.array(np.full(k, ds), pa.string()),
        pa.array(np.arange(k, dtype=np.int64)),
        pa.array(np.full(k, "real"), pa.string()),
        pa.array(p["gps_time"].to_numpy()[kept]),
        pa.array(sensor_rec[kept, 0]), pa.array(sensor_rec[kept, 1]), pa.array(sensor_rec[kept, 2]),
        pa.array(d[kept, 0]), pa.array(d[kept, 1]), pa.array(d[kept, 2]),
        pa.array(anchor[kept, 0]), pa.array(anchor[kept, 1]), pa.array(anchor[kept, 2]),
        pa.array(echo_ns[kept, 0] * RANGE_PER_NS),
        pa.array(p["scan_angle_deg"].to_numpy()[kept]),
        pa.array(agc[kept].astype(np.float64)),
        pa.array(np.full(k, sensor.sampling_ns)),
        pa.array(np.full(k, DIGITIZER_GAIN)), pa.array(np.full(k, DIGITIZER_OFFSET)),
        padded_to_list(samples[kept].astype(np.float32), np.full(k, n_s), pa.float32()),
        pa.array(lengths.astype(np.int16)),
        lst(echo_xyz[:, :, 0], pa.float64()), lst(echo_xyz[:, :, 1], pa.float64()), lst(echo_xyz[:, :, 2], pa.float64()),
        lst(echo_t, pa.float64()),
        lst(inten.astype(np.float32), pa.float32()),
    ], schema=PULSE_SCHEMA)
    date = pd.Timestamp(str(row["campaign_date"]))
    las = out / f"{ds}.las"
    write_waveform_las(las, table, version="1.4", point_format=9, bits=8, storage="internal",
                       agc_attribute="user_data", creation=(int(date.day_of_year), int(date.year)),
                       system_identifier="ALS60 (virtual)", generating_software=f"waveforest {__version__}",
                       wkt=wkt)
    off = strip_off[traj["strip"].to_numpy()] + np.column_stack([traj_xy, np.zeros(len(traj))])
    traj_out = pd.DataFrame({"gps_time": traj["gps_time"], "x": traj["x"] + off[:, 0],
                             "y": traj["y"] + off[:, 1], "z": traj["z"] + off[:, 2]})
    traj_out.to_csv(out / f"{ds}_trajectory.csv", index=False, float_format="%.4f")

    info = _dataset_info(row, sensor, plan, p, agc, kept, keep, lengths, strip_off)
    truth = pd.DataFrame({
        "dataset": ds, "gps_time": p["gps_time"].to_numpy(), "recorded": keep, "site": p["site"].to_numpy(),
        "strip": p["strip"].to_numpy(), "sensor_x": sensor_true[:, 0], "sensor_y": sensor_true[:, 1],
        "sensor_z": sensor_true[:, 2], "dir_x": d[:, 0], "dir_y": d[:, 1], "dir_z": d[:, 2],
        "ground_x": p["ground_x"].to_numpy(), "ground_y": p["ground_y"].to_numpy(), "ground_z": p["ground_z"].to_numpy(),
        "range_ground_m": p["range_ground_m"].to_numpy(), "a0_dn": a0, "agc": agc, "gain": gain,
        "observed_peak_dn": observed, "xy_offset_x": xy[:, 0], "xy_offset_y": xy[:, 1],
        "first_echo_range_m": echo_ns[:, 0] * RANGE_PER_NS, "first_echo_amp_dn": echo_amp[:, 0],
        "first_echo_walk_m": walk[:, 0]})
    return table, info, truth


def _record_sites(sensor: TruthSensor, batches, gain: np.ndarray, n: int, eff: dict, seed: int, ds: str):
    """The sensor's records of a dataset's n pulses, site by site (:func:`.truth_sensor.record`).

    ``batches``: (site, rows, sigma, t0_ns, range_m) per site; stream ("sensor", ds, site).
    Returns samples (n, n_s) uint8, first_sample_ns (n,), echo_ns, echo_amp_dn (n, 4), intensity
    (n, 4) uint8, n_echoes (n,) int64 and walk_m (n, 4); rows of no batch keep NaN / 0.
    """
    n_s = sensor.n_samples
    samples = np.zeros((n, n_s), dtype=np.uint8)
    first = np.full(n, np.nan)
    echo_ns = np.full((n, MAX_ECHOES), np.nan)
    echo_amp = np.full((n, MAX_ECHOES), np.nan)
    inten = np.zeros((n, MAX_ECHOES), dtype=np.uint8)
    n_echo = np.zeros(n, dtype=np.int64)
    walk = np.full((n, MAX_ECHOES), np.nan)
    for site, rows, sig, t0, rg in batches:
        rec = record(sensor, sig, t0, rg, gain[rows], stream_generator(seed, "sensor", ds, site),
                     noise_autocorr=eff["noise_autocorr"], nonlinearity=eff["nonlinearity"],
                     trigger_loss=eff["trigger_loss"])
        samples[rows], first[rows], echo_ns[rows] = rec.samples, rec.first_sample_ns, rec.echo_ns
        echo_amp[rows], inten[rows], n_echo[rows], walk[rows] = rec.echo_amp_dn, rec.intensity, rec.n_echoes, rec.walk_m
    return samples, first, echo_ns, echo_amp, inten, n_echo, walk


def _dataset_info(row, sensor: TruthSensor, plan, p: pd.DataFrame, agc: np.ndarray, kept: np.ndarray,
                  keep: np.ndarray, lengths: np.ndarray, strip_off: np.ndarray) -> dict:
    """The dataset's entry of ``truth.json``: counts, the AGC law at the mean AGC, noise, the true
    S(t), the sensor, and the strips with their positioning offsets."""
    n, k = len(p), len(kept)
    a_mean = float(np.mean(agc[kept])) if k else float("nan")
    law = sensor.agc
    c = law.scale_at(a_mean)
    info = {
        "year": int(row["year"]),
        "n_pulses": int(k), "n_points": int(lengths.sum()),
        "n_without_echo": int(n - k),
        "n_target_pulses": int(np.sum(keep & (p["kind"] == "target").to_numpy())),
        "a": a_mean, "b": law.b_at(a_mean),
        "agc": {"law": "gain = 1 + (AGC - law_a) * law_b on the signal (Eq. 1); a = dataset mean AGC, "
                       "b = law_b / (1 + (a - law_a) law_b) describes the same law with reference a",
                "law_a": law.law_a, "law_b": law.law_b, "a_mean": a_mean, "b_at_a_mean": law.b_at(a_mean),
                "gain_at_a_mean": c, "loop": {kk: getattr(law, kk) for kk in (
                    "bg_mean", "bg_sd", "bg_tau_s", "loop_tau_s", "loop_gain", "setpoint_dn", "jitter_sd")},
                "agc_min": int(agc[kept].min()) if k else None, "agc_max": int(agc[kept].max()) if k else None},
        "noise_mean_dn": sensor.noise_mean_dn, "noise_sd_dn": sensor.noise_sd_dn,
        "pulse_fwhm_ns": sensor.system.fwhm_ns,
        "system_waveform": {
            "units": "DN m^2 per unit sigma (Eq. 7); t = 0 at the sensor's DR time of a spike target",
            "t_ns": sensor.system.t_ns, "s": sensor.system.s, "s_at_a_mean": sensor.system.s * c},
        "sensor": sensor.manifest(),
        "strips": [{"index": st.index, "azimuth_deg": st.azimuth_deg, "w_line_m": st.w_line,
                    "t_start": st.t_start, "duration_s": st.duration, "altitude_m": st.z_fly,
                    "offset_xyz_m": strip_off[st.index]} for st in plan.strips],
    }
    return info


def _write_tables(out: Path, datasets: pd.DataFrame, fields: pd.DataFrame, targets: pd.DataFrame,
                  density_scale: float) -> None:
    d = pd.DataFrame({
        "dataset": datasets["dataset"], "year": datasets["year"],
        "las_file": datasets["dataset"] + ".las", "trajectory_file": datasets["dataset"] + "_trajectory.csv",
        "mean_range_m": datasets["mean_range_m"], "pulse_width_fwhm_ns": datasets["pulse_width_fwhm_ns"],
        "footprint_diameter_m": datasets["footprint_diameter_m"], "divergence_mrad": datasets["divergence_mrad"],
        "sampling_ns": datasets["sampling_ns"],
        "pulse_density_m2": datasets["pulse_density_m2"] * float(density_scale),
        "max_scan_zenith_deg": datasets["max_scan_zenith_deg"]})
    d.to_csv(out / "datasets.csv", index=False)
    f = fields[FIELD_COLUMNS].copy()
    f.to_csv(out / "fields.csv", index=False, float_format="%.3f")
    t = targets[TARGET_COLUMNS].copy()
    t.to_csv(out / "targets.csv", index=False, float_format="%.3f")
