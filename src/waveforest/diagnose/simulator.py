"""The study's real simulation chain as the diagnosis's ``simulate(pulses, effects, seed)``.

A thin adapter over :func:`waveforest.stages.simulate.simulate_pulses` (vegetation ->
MCRT -> sensor -> CFD; effects routed to the module that applies each) and
:func:`waveforest.sensor.feature_table` (first-echo features, the same code as for the real
pulses). It adds four things:

* **the seed**: ``simulate_pulses`` derives every random number from the config's master
  seed, the dataset, the sample and the vegetation instance; the adapter passes the search's
  seed as that master seed, so one seed gives the same plants, rays and noise for every
  effect value (common random numbers) and another seed an independent replicate;
* **scene reuse**: a cache of prepared (Embree) scenes keyed by species, height, scene seed
  and vegetation keyword arguments. Effects that do not act on the plants (``mcrt``,
  ``sensor`` and ``geometry`` stages: specular, hotspot, noise_autocorr, nonlinearity,
  trigger_loss, xy_error) therefore trace the very same instances as the model without them
  (no rebuild, and no extra vegetation noise between values); only the four vegetation
  effects build new ones;
* **S(t) of the model tried**: the calibrate stage inverts the sensor effects of the base
  model (``simulate.effects``) on the calibration targets (:func:`waveforest.sensor.calibration.linearise`);
  a candidate ``nonlinearity`` or ``trigger_loss`` shapes those targets too, so with the
  targets' pulses (``calibration_pulses``) each value tried gets S(t) recalibrated under it
  (cached per value). Without them the candidate is applied on top of the calibrated S(t),
  which already holds part of the effect;
* **the selection rules mirrored on the simulation**: real pulses were selected with their
  first echo at least ``select.tree_min_echo_h_m`` above the ground for trees; a simulated
  twin whose first echo is lower is dropped in the same way, and the waveform features of
  species in ``simulate.compare_min_h_m`` (birch: 1.5 m) use only pulses whose first echo is
  higher, for real and simulated pulses alike (:func:`apply_rules`, as ``compare`` does).
  The pulses under the crowns (``stratum`` "below crown") are one population on both sides,
  drawn by one rule and one detector. Real: every pulse whose own first CFD echo (found as a
  twin's is, :func:`own_cfd_echoes`) lies within ``select.tree_radius_m`` of a compared stem
  and lower than ``select.tree_min_echo_h_m`` (:func:`.run.with_pulses_under_crowns`). Twin:
  for each such pulse, the first of up to :data:`BELOW_CROWN_ATTEMPTS` traces of its beam
  whose first echo meets the same rule, the beam turned about the stem by a seeded azimuth
  from the second attempt on (:func:`turned_about_stems`: each point keeps its height and
  its distance from the stem) with rays, noise and ``xy_error`` offsets drawn anew. A real
  pulse of the stratum went through a gap of its plant; its twin is the same beam through a
  gap of the twin's plant, so both sides are draws of "what lies under the crown at that
  distance and angle". (With one trace per pulse only the twins whose plant happened to
  have a gap there stayed, 4-17 per dataset on a campaign of 40 birches per year, weighted
  towards beams that pass easily; with up to 16, about 49 of the 54 pulses of its 2012
  dataset get a twin, and without effects the stratum's H, E and Apeak differ from the real
  by d = +0.02, -0.01, -0.06. Drawing the real side by the sensor's DR echo instead left
  out the pulses whose DR fired on a weak crown return that the CFD passes over, half of
  them with a first echo on low branches at 0.6-1 m, while their twins kept theirs.) The
  adapter simulates every pulse it is given, so it marks them all ``comparison_set`` for
  ``simulate_pulses``.
"""

from __future__ import annotations

import copy
from collections import OrderedDict
from dataclasses import replace

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError
from waveforest.io.pulses import list_to_padded, padded_to_list
from waveforest.io.tables import dataset_row
from waveforest.mcrt import prepare
from waveforest.model.forward import SensorSetup, hash_ids, stable_hash, twin_echoes
from waveforest.sensor import CFDParams, FeatureParams, feature_table, range_correction_of
from waveforest.sensor._checks import gain_or_one
from waveforest.sensor.agc import GAIN_COLUMN
from waveforest.sensor.calibration import calibration_effects
from waveforest.stages.simulate import simulate_pulses
from waveforest.vegetation import build_scene, species_table

BELOW_CROWN = "below crown"
"""``stratum`` of the pulses of ``select``'s ``below_crown_set`` (the others have "")."""

BELOW_CROWN_ATTEMPTS = 16
"""Most attempts at a twin under the crown per pulse of that stratum (:meth:`StudySimulator._below_crown`)."""

WAVEFORM_FEATURES = ("Npeaks", "Apeak", "FWHM", "E")
"""Features restricted by ``simulate.compare_min_h_m`` (all but H)."""

SCENE_CACHE_SIZE = 512
"""Most prepared scenes kept (least recently used dropped first) ..."""

SCENE_CACHE_TRIANGLES = 12_000_000
"""... and most triangles in them (a prepared scene with its Embree BVH takes roughly
100 bytes per triangle; a low-species plot has ~200 000 triangles)."""


def apply_rules(features: pd.DataFrame, cfg: dict) -> pd.DataFrame:
    """The selection rules of ``select`` and ``compare`` applied to a feature table.

    Rows of trees (``is_tree``) whose first echo lies below ``select.tree_min_echo_h_m`` are
    dropped (``select``'s rule, which the real pulses satisfy by construction), and so are
    rows of the stratum "below crown" whose first echo lies at or above it (the mirror
    rule); for species in ``simulate.compare_min_h_m`` the waveform features of the other
    rows with H at or below the threshold become NaN (``compare``'s rule, docs/method.md §(i1)).
    Rows without a first echo (H NaN) are dropped.

    Parameters
    ----------
    features : DataFrame
        Feature table with species, H, the waveform features and optionally is_tree and
        stratum.
    cfg : dict
        Loaded study config.
    """
    df = features[np.isfinite(features["H"].to_numpy(dtype=float))].copy()
    below = (df["stratum"].astype(str) == BELOW_CROWN).to_numpy() if "stratum" in df else np.zeros(len(df), bool)
    if "is_tree" in df.columns:
        tree = df["is_tree"].fillna(False).astype(bool).to_numpy()
        high = df["H"].to_numpy(float) >= float(cfg["select"]["tree_min_echo_h_m"])
        keep = np.where(below, ~high, ~tree | high)
        df, below = df[keep].copy(), below[keep]
    species = df["species"].astype(str).to_numpy()
    h = df["H"].to_numpy(float)
    for sp, lo in cfg["simulate"]["compare_min_h_m"].items():
        low = (species == sp) & ~(h > float(lo)) & ~below
        for f in WAVEFORM_FEATURES:
            if f in df.columns:
                df.loc[low, f] = np.nan
    return df.reset_index(drop=True)


def turned_about_stems(pulses: pa.Table, azimuth) -> pa.Table:
    """``pulses`` with each beam turned about its sample's vertical axis by ``azimuth`` (rad):
    the sensor position and anchor about (sample_x, sample_y), the direction with them.
    Heights, ranges and each point's distance from the stem are kept (echo lists are not
    turned; the simulation does not read them)."""
    c, s = np.cos(np.asarray(azimuth, float)), np.sin(np.asarray(azimuth, float))
    x0, y0 = (pulses.column(k).to_numpy(zero_copy_only=False).astype(float) for k in ("sample_x", "sample_y"))
    out = pulses
    for x, y, origin in (("sensor_x", "sensor_y", (x0, y0)), ("anchor_x", "anchor_y", (x0, y0)),
                         ("dir_x", "dir_y", (0.0, 0.0))):
        u = out.column(x).to_numpy(zero_copy_only=False).astype(float) - origin[0]
        v = out.column(y).to_numpy(zero_copy_only=False).astype(float) - origin[1]
        out = out.set_column(out.schema.get_field_index(x), x, pa.array(origin[0] + c * u - s * v))
        out = out.set_column(out.schema.get_field_index(y), y, pa.array(origin[1] + s * u + c * v))
    return out


def stem_distance(pulses: pa.Table, z) -> np.ndarray:
    """Horizontal distance (m) from (sample_x, sample_y) of the point at height ``z`` (m) on
    each pulse's recorded beam line (sensor + s dir)."""
    col = {c: pulses.column(c).to_numpy(zero_copy_only=False).astype(float)
           for c in ("sensor_x", "sensor_y", "sensor_z", "dir_x", "dir_y", "dir_z", "sample_x", "sample_y")}
    s = (np.asarray(z, float) - col["sensor_z"]) / col["dir_z"]
    return np.hypot(col["sensor_x"] + col["dir_x"] * s - col["sample_x"], col["sensor_y"] + col["dir_y"] * s
                    - col["sample_y"])


def own_cfd_echoes(pulses: pa.Table, calibration, cfg: dict) -> pa.Table:
    """``pulses`` with their DR echoes replaced by the CFD echoes of their own waveforms.

    The CFD, its range correction and its arming on the recorded noise (noise SD / AGC gain)
    are those that give a simulated twin its echoes (:func:`waveforest.model.forward.twin_echoes`);
    times, amplitudes and positions (on the recorded beam line, anchor + dir t c/2, as a
    twin's) replace the DR's. A pulse without a CFD echo is left out, as a twin without one is.

    Parameters
    ----------
    pulses : pa.Table
        AGC-normalised pulse rows of one dataset (``agc`` or ``select`` table rows).
    calibration : waveforest.stages.simulate.Calibration
        The dataset's calibration (CFD, range correction, noise).
    cfg : dict
        Loaded study config (``sensor.cfd`` when the calibration has no CFD).
    """

    samples, lengths = list_to_padded(pulses.column("samples"))
    sampling = pulses.column("sampling_ns").to_numpy(zero_copy_only=False)
    gain = gain_or_one(pulses.column(GAIN_COLUMN).to_numpy(zero_copy_only=False)) if GAIN_COLUMN in \
        pulses.column_names else None
    setup = SensorSetup.from_config(cfg, calibration.system, calibration.noise_mean, calibration.noise_sd,
                                    float(sampling[0]) if len(sampling) else 1.0,
                                    range_correction=calibration.range_correction, cfd=calibration.cfd)
    echoes = twin_echoes(samples, lengths, sampling, setup, gain)
    times, counts = np.nan_to_num(echoes.times_ns), echoes.n_echoes.astype(np.int64)
    columns = {"echo_time_ns": padded_to_list(times, counts, pa.float64()),
               "echo_intensity": padded_to_list(np.nan_to_num(echoes.amplitudes).astype(np.float32), counts,
                                                pa.float32()),
               "n_echoes": pa.array(counts.astype(np.int16))}
    for axis in "xyz":
        anchor = pulses.column(f"anchor_{axis}").to_numpy(zero_copy_only=False).astype(float)
        direction = pulses.column(f"dir_{axis}").to_numpy(zero_copy_only=False).astype(float)
        columns[f"echo_{axis}"] = padded_to_list(anchor[:, None] + direction[:, None] * times * RANGE_PER_NS,
                                                 counts, pa.float64())
    out = pulses
    for name, values in columns.items():
        out = out.set_column(out.schema.get_field_index(name), name, values)
    return out.filter(pa.array(counts > 0))


def _is_tree_model(species: str) -> bool:
    """Whether ``build_scene`` grows the understory layer under this species (tree models)."""

    t = species_table()
    row = t[t["slug"] == species]
    return bool(row["model"].iloc[0] == "tree") if len(row) else True


class _SceneCache:
    """``scene_builder`` for ``simulate_pulses`` that returns cached prepared scenes.

    The BVH is built at MEDIUM quality: a scene serves a few pulses of ``diagnose.n_rays``
    (2,000) per simulation, far below what a HIGH build pays back over
    (:func:`waveforest.mcrt.tracer.bvh_quality`); measured on the slow-test campaign of
    ``tests/test_diagnose_run.py``, a half-sample simulation with new plants takes 5.0 s
    instead of 10.0 s, one that re-traces cached scenes the same 1.1-1.3 s.
    """

    def __init__(self, size: int = SCENE_CACHE_SIZE, triangles: int = SCENE_CACHE_TRIANGLES):
        self.size = size
        self.max_triangles = triangles
        self.triangles = 0
        self.scenes: OrderedDict = OrderedDict()
        self.built = 0
        self.hits = 0

    def __call__(self, species, height, seed, **kwargs):

        kw = {k: float(v) for k, v in kwargs.items()}
        if kw.get("understory", 0.0) and not _is_tree_model(str(species)):
            kw.pop("understory")  # grows under trees only (vegetation.build_scene): same plant
        key = (str(species), float(height), int(seed), tuple(sorted(kw.items())))
        if key in self.scenes:
            self.scenes.move_to_end(key)
            self.hits += 1
            return self.scenes[key]
        scene = prepare(build_scene(species, height, seed, **kwargs), quality="medium")
        self.built += 1
        self.scenes[key] = scene
        self.triangles += len(scene.scene)
        while len(self.scenes) > 1 and (len(self.scenes) > self.size or self.triangles > self.max_triangles):
            _, old = self.scenes.popitem(last=False)
            self.triangles -= len(old.scene)
        return scene


class StudySimulator:
    """``simulate(pulses, effects, seed) -> feature table`` over the study's real chain.

    Parameters
    ----------
    selected : dict
        Dataset -> ``select`` pulse table (pa.Table) of that dataset.
    datasets : DataFrame
        The campaign's datasets.csv (:func:`waveforest.io.tables.read_datasets`).
    calibrations : dict
        Dataset -> (Calibration of :mod:`waveforest.stages.simulate`, calibration JSON dict).
    cfg : dict
        Loaded study config.
    n_rays : int, optional
        MCRT rays per pulse (default ``diagnose.n_rays``, at most ``mcrt.n_rays``).
    threads : int, optional
        Threads of each MCRT call.
    base_effects : dict, optional
        Effects of the base model (``simulate.effects``), under every call's ``effects``.
    range_correction : bool
        Apply the calibration's CFD range correction to the features' own CFD echoes (as
        the ``features`` stage does with ``sensor.cfd.range_correction``).
    calibration_pulses : dict, optional
        Dataset -> :class:`waveforest.sensor.calibration.CalibrationPulses`, to recalibrate
        S(t) under the sensor effects tried (module docstring).
    """

    def __init__(self, selected: dict, datasets: pd.DataFrame, calibrations: dict, cfg: dict, *,
                 n_rays: int | None = None, threads: int | None = None, base_effects: dict | None = None,
                 range_correction: bool = True, calibration_pulses: dict | None = None):

        self.selected = selected
        self.info = {ds: dataset_row(datasets, ds) for ds in selected}
        missing = sorted(set(selected) - set(calibrations))
        if missing:
            raise WaveforestError(f"diagnose: no calibration for dataset(s) {', '.join(missing)}")
        self.calibrations = calibrations
        self.cfg = cfg
        self.n_rays = int(n_rays or min(cfg["diagnose"]["n_rays"] or cfg["mcrt"]["n_rays"], cfg["mcrt"]["n_rays"]))
        self.base_effects = dict(base_effects or {})
        self.range_correction = bool(range_correction)
        self.threads = threads
        self.scenes = _SceneCache()
        self.pulses_simulated = 0
        self.calibration_pulses = dict(calibration_pulses or {})
        self._recalibrated: dict = {}

    def calibration(self, dataset: str, effects: dict) -> tuple:
        """(Calibration, calibration JSON) of ``dataset`` for a model with ``effects`` (all of them).

        The calibrate stage's own when the calibration-shaping sensor effects are those of the
        base model or no target pulses were given; else S(t) recalibrated under them.
        """

        wanted = calibration_effects(effects)
        if wanted == calibration_effects(self.base_effects) or dataset not in self.calibration_pulses:
            return self.calibrations[dataset]
        key = (dataset, tuple(sorted(wanted.items())))
        if key not in self._recalibrated:
            cal, meta = self.calibrations[dataset]
            system = self.calibration_pulses[dataset].system_waveform(wanted)
            self._recalibrated[key] = (replace(cal, system=system), {**meta, "fwhm_ns": system.fwhm_ns})
        return self._recalibrated[key]

    def _cfg(self, seed: int) -> dict:
        c = copy.deepcopy(self.cfg)
        c["seed"] = int(seed) % 2**63
        c["mcrt"]["n_rays"] = self.n_rays
        c["simulate"]["max_pulses"] = None
        c["simulate"]["instances_per_sample"] = self.cfg["diagnose"]["instances_per_sample"]
        return c

    def _features(self, sub: pa.Table, ds: str, model: dict, cfg: dict, stream: int = 0) -> pd.DataFrame | None:
        """Feature table of the twins of the rows of ``sub`` (one dataset); None when none has an echo."""

        cal, meta = self.calibration(ds, model)
        sim, _ = simulate_pulses(sub, self.info[ds], cal, cfg, effects=model, progress=False, threads=self.threads,
                                 scene_builder=self.scenes, stream=stream)
        self.pulses_simulated += sub.num_rows
        if sim.num_rows == 0:
            return None
        rc = {ds: range_correction_of(meta)} if self.range_correction else None
        return feature_table(sim, {ds: meta}, FeatureParams.from_config(cfg), cfd=cal.cfd or CFDParams.from_config(cfg),
                             range_corrections=rc)

    def _below_crown(self, sub: pa.Table, ds: str, model: dict, cfg: dict) -> list[pd.DataFrame]:
        """Twins of the pulses under the crowns: for each, the first of up to
        :data:`BELOW_CROWN_ATTEMPTS` attempts whose first echo meets ``select``'s rule for the
        stratum (lower than ``select.tree_min_echo_h_m``, within ``select.tree_radius_m`` of the
        stem on the recorded beam line); attempt k > 0 turns the beam about the stem by a seeded
        azimuth (:func:`turned_about_stems`) and draws rays, noise and offsets anew (random
        stream k) over the same plant."""

        low, radius = float(self.cfg["select"]["tree_min_echo_h_m"]), float(self.cfg["select"]["tree_radius_m"])
        found = []
        for k in range(BELOW_CROWN_ATTEMPTS):
            if sub.num_rows == 0:
                break
            ids = sub.column("pulse_id").to_numpy()
            turned = sub if k == 0 else turned_about_stems(
                sub, hash_ids(stable_hash(int(cfg["seed"]), ds, "azimuth", k), ids) / 2.0**64 * 2.0 * np.pi)
            feats = self._features(turned, ds, model, cfg, stream=k)
            if feats is None:
                continue
            order = np.argsort(ids)
            rows = turned.take(pa.array(order[np.searchsorted(ids, feats["pulse_id"].to_numpy(np.int64),
                                                              sorter=order)]))
            under = (feats["H"].to_numpy(float) < low) & (stem_distance(rows, feats["echo_z"].to_numpy(float))
                                                          <= radius)
            found.append(feats[under])
            sub = sub.filter(pa.array(~np.isin(ids, feats["pulse_id"].to_numpy(np.int64)[under])))
        return found

    def __call__(self, pulses: pd.DataFrame, effects: dict, seed: int) -> pd.DataFrame:
        """Simulate the rows of ``pulses`` (dataset, pulse_id) under ``effects``.

        Returns
        -------
        DataFrame
            Feature table of the simulated pulses (dataset, pulse_id, sample_id, species,
            is_tree, H, Npeaks, Apeak, FWHM, E, n_echoes, ...), selection rules applied.
        """
        cfg = self._cfg(seed)
        model = {**self.base_effects, **effects}
        parts = []
        for ds, rows in pulses.groupby("dataset", sort=True):
            if ds not in self.selected:
                raise WaveforestError(f"diagnose: no select table for dataset {ds}")
            table = self.selected[ds]
            below = rows.loc[rows["stratum"] == BELOW_CROWN, "pulse_id"] if "stratum" in rows else []
            ids = rows["pulse_id"].to_numpy(np.int64)
            sub = table.filter(pc.is_in(table.column("pulse_id"), value_set=pa.array(ids)))
            sub = sub.set_column(sub.schema.get_field_index("comparison_set"), "comparison_set",
                                 pa.array(np.ones(sub.num_rows, bool)))
            under = np.isin(sub.column("pulse_id").to_numpy(), np.asarray(below, np.int64))
            feats = [self._features(sub.filter(pa.array(~under)), ds, model, cfg)] if (~under).any() else []
            feats += self._below_crown(sub.filter(pa.array(under)), ds, model, cfg) if under.any() else []
            feats = [f for f in feats if f is not None]
            if not feats:
                continue
            feats = pd.concat(feats, ignore_index=True)
            if "stratum" in rows.columns:  # the twin is in its real pulse's stratum (apply_rules)
                feats = feats.merge(rows[["pulse_id", "stratum"]], on="pulse_id", how="left", validate="one_to_one")
            parts.append(feats)
        if not parts:
            raise WaveforestError("diagnose: the simulation produced no pulse with an echo")
        return apply_rules(pd.concat(parts, ignore_index=True), self.cfg)
