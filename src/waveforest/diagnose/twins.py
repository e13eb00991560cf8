"""The study's real simulation chain as the diagnosis's ``simulate(pulses, effects, seed)``.

A thin adapter over :func:`waveforest.model.simulate.simulate_pulses` (vegetation ->
MCRT -> sensor -> CFD; effects routed to the module that applies each) and
:func:`waveforest.sensor.feature_table` (first-echo features, the same code as for the real
pulses) with :func:`.waveform.waveform_statistics` (the whole waveform). It adds five things:

* **the seed**: ``simulate_pulses`` derives every random number from the settings' master
  seed, the dataset, the sample and the vegetation instance; the adapter passes the search's
  seed as that master seed (the study's :class:`~waveforest.model.simulate.SimulateSettings`
  with the seed replaced), so one seed gives the same plants, rays and noise for every
  effect value (common random numbers) and another seed an independent replicate;
* **scene reuse**: a cache of prepared (Embree) scenes keyed by species, height, scene seed
  and vegetation keyword arguments. Effects that do not act on the plants (``mcrt``,
  ``sensor`` and ``geometry`` stages: specular, hotspot, noise_autocorr, nonlinearity,
  trigger_loss, xy_error) therefore trace the very same instances as the model without them
  (no rebuild, and no extra vegetation noise between values); only the four vegetation
  effects build new ones, and ``leaf_albedo``, which changes the leaves' optics only, reuses
  the BVH of the plant without it;
* **trace reuse**: a model whose sigma(t) is the base model's (it adds sensor effects only:
  noise_autocorr, nonlinearity, trigger_loss) takes the base model's traces of the same seed
  from a cache (:class:`TraceCache`) and renders them under its own sensor;
* **S(t) of the model tried**: the calibrate stage inverts the sensor effects of the base
  model (``simulate.effects``) on the calibration targets (:func:`waveforest.sensor.calibration.linearise`);
  a candidate ``nonlinearity`` or ``trigger_loss`` shapes those targets too, so with the
  targets' pulses (``calibration_pulses``) each value tried gets S(t) recalibrated under it
  (cached per value). Without them the candidate is applied on top of the calibrated S(t),
  which already holds part of the effect;
* **the selection rules mirrored on the simulation** (:mod:`.strata`): a simulated twin
  is dropped or masked by the rules that selected its real pulse
  (:func:`.strata.apply_rules`); a twin of the stratum under the crowns is the first of up
  to :data:`.strata.BELOW_CROWN_ATTEMPTS` traces of its beam, turned about the stem from the
  second attempt on (:func:`.strata.turned_about_stems`), whose first echo meets that
  stratum's rule; a twin of the ring (:data:`.strata.RING`) is dropped when its own first echo
  lies within ``select.tree_radius_m`` of the stem, where a sample would have taken its real
  pulse. The adapter simulates every pulse it is given, so it marks them all
  ``comparison_set`` for ``simulate_pulses``.

Contract: ``StudySimulator(...)(pulses, effects, seed)`` takes rows with dataset and
pulse_id (and optionally stratum) and returns a feature table (one row per twin with an
echo; H in m, FWHM in ns, Apeak in DN, E in DN ns). Errors:
:class:`waveforest.errors.WaveforestError` for a dataset without select table or
calibration, and when no twin has an echo. Measured costs: docs/validation.md (Speed).
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from collections import OrderedDict
from dataclasses import fields, replace

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from waveforest.diagnose.catalogue import VEGETATION_EFFECTS
from waveforest.diagnose.settings import DiagnoseSettings
from waveforest.diagnose.strata import (
    BELOW_CROWN,
    BELOW_CROWN_ATTEMPTS,
    RING,
    apply_rules,
    stem_distance,
    turned_about_stems,
)
from waveforest.diagnose.waveform import WAVEFORM_FEATURES, waveform_statistics
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.io.tables import dataset_row
from waveforest.mcrt import prepare, trace, with_optics
from waveforest.model.forward import split_effects
from waveforest.model.simulate import SimulateSettings, simulate_pulses
from waveforest.rng import hash_ids, stable_hash
from waveforest.sensor import feature_table, range_correction_of
from waveforest.sensor.calibration import calibration_effects
from waveforest.vegetation import build_scene, species_table

SCENE_CACHE_SIZE = 512
"""Most prepared scenes kept (least recently used dropped first) ..."""

SCENE_CACHE_TRIANGLES = 24_000_000
"""... and most triangles in them (a prepared scene with its Embree BVH takes ~300-400 bytes
per triangle, so ~8 GB; a low-species plot has ~240 000 triangles). The scenes of the
default study's diagnosis (diagnose.pulses_per_species) fit; beyond it, every simulation builds
the plants that do not fit again (:class:`SceneCache` keeps the others)."""

TRACE_CACHE_BYTES = 1 << 30
"""Most bytes of sigma(t) the :class:`TraceCache` keeps (least recently used dropped first):
16 kB per pulse at the default 100-ns window, so the base model's traces of every pulse over
the power analysis' and the search's seeds."""


def _is_tree_model(species: str) -> bool:
    """Whether ``build_scene`` grows the understory layer under this species (tree models)."""

    t = species_table()
    row = t[t["slug"] == species]
    return bool(row["model"].iloc[0] == "tree") if len(row) else True


def _vegetation_effects(species: str, kw: dict) -> tuple:
    """The vegetation effects in ``build_scene`` keyword arguments that change this species'
    plant: sorted (name, value) pairs, off values and an understory under a non-tree dropped."""
    return tuple(sorted((k, float(v)) for k, v in kw.items() if k in VEGETATION_EFFECTS
                        and float(v) != CATALOGUE[k].off and (k != "understory" or _is_tree_model(species))))


class SceneCache:
    """``scene_builder`` for ``simulate_pulses`` that returns cached prepared scenes.

    Keyed by (species, height, scene seed, vegetation keyword arguments); least recently
    used scenes are dropped beyond :data:`SCENE_CACHE_SIZE` scenes or
    :data:`SCENE_CACHE_TRIANGLES` triangles, except those used in the current pass
    (:meth:`new_pass`: one simulation): when the plants of one simulation do not all fit, the
    newest is dropped instead, so that the next simulation over the same plants finds the
    others (a least-recently-used cache smaller than the cycle it serves misses on every
    request). Plants of the base model (``base_effects``'
    vegetation effects) are kept from their first build; plants under other vegetation
    effects (a candidate's value, mostly asked for once) only from their second request, so
    that one-off plants do not push out the ones every other candidate traces again. A plant
    under ``leaf_albedo`` is the plant without it with new leaf optics
    (:func:`waveforest.mcrt.with_optics`): no BVH of its own. The BVH
    is built at MEDIUM quality: a scene serves a few pulses of ``diagnose.n_rays`` per
    simulation, far below what a HIGH build pays back over
    (:func:`waveforest.mcrt.tracer.bvh_quality`; timings in docs/validation.md).
    """

    def __init__(self, size: int = SCENE_CACHE_SIZE, triangles: int = SCENE_CACHE_TRIANGLES,
                 base_effects: dict | None = None):
        self.size = size
        self.max_triangles = triangles
        self.base_effects = dict(base_effects or {})
        self.triangles = 0
        self.scenes: OrderedDict = OrderedDict()
        self.requested: set = set()  # keys of plants built once and not kept
        self.used: dict = {}  # key -> pass of its last request
        self.passes = 0
        self.built = 0
        self.hits = 0
        self.lock = threading.Lock()

    def __call__(self, species, height, seed, **kwargs):

        species = str(species)
        fx = _vegetation_effects(species, kwargs)
        rest = tuple(sorted((k, float(v)) for k, v in kwargs.items() if k not in VEGETATION_EFFECTS))
        key = (species, float(height), int(seed), rest + fx)
        base = fx == _vegetation_effects(species, self.base_effects)
        with self.lock:
            if key in self.scenes:
                self.scenes.move_to_end(key)
                self.used[key] = self.passes
                self.hits += 1
                return self.scenes[key]
        # built outside the lock (simulate_pulses' worker threads build concurrently)
        if any(name == "leaf_albedo" for name, _ in fx):  # optics only: the BVH of the plant without it
            geometry = self(species, height, seed, **{**kwargs, "leaf_albedo": CATALOGUE["leaf_albedo"].off})
            scene = with_optics(geometry, build_scene(species, height, seed, **kwargs))
        else:
            scene = prepare(build_scene(species, height, seed, **kwargs), quality="medium")
        with self.lock:
            self.built += 1
            keep = base or key in self.requested
            if not keep:
                self.requested.add(key)
            elif key not in self.scenes:
                self.scenes[key] = scene
                self.used[key] = self.passes
                self.triangles += len(scene.scene)
            while len(self.scenes) > 1 and (len(self.scenes) > self.size or self.triangles > self.max_triangles):
                oldest = next(iter(self.scenes))
                drop = next(reversed(self.scenes)) if self.used[oldest] == self.passes else oldest
                self.triangles -= len(self.scenes.pop(drop).scene)
                del self.used[drop]
        return scene

    def new_pass(self) -> None:
        """Start a pass (one simulation): plants requested before it may be dropped first."""
        with self.lock:
            self.passes += 1


def _digest(beams, seed, kwargs: dict) -> bytes:
    """A digest of a trace's beams, seed and keywords (arrays by dtype, shape and bytes)."""
    h = hashlib.blake2b(digest_size=20)
    items = [(f.name, getattr(beams, f.name)) for f in fields(beams)] + [("seed", seed)] + sorted(kwargs.items())
    for name, value in items:
        h.update(name.encode())
        if isinstance(value, np.ndarray):
            a = np.ascontiguousarray(value)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        else:
            h.update(repr(value).encode())
    return h.digest()


class TraceCache:
    """``tracer`` for ``simulate_pulses`` that keeps the results of :func:`waveforest.mcrt.trace`.

    A trace is a function of the scene, the beams, the seed and the keywords, not of the
    threads (:mod:`waveforest.mcrt.tracer`): the key is the scene's identity and a digest of
    the rest, and each entry holds a weak reference to its scene, so that a scene the
    :class:`SceneCache` dropped ends its entries. The adapter passes it for the models whose
    sigma(t) is the base model's (they differ in sensor effects only): with common random
    numbers their values trace nothing anew. Bounded by :data:`TRACE_CACHE_BYTES` of sigma.
    """

    def __init__(self, max_bytes: int = TRACE_CACHE_BYTES):
        self.max_bytes = int(max_bytes)
        self.entries: OrderedDict = OrderedDict()
        self.bytes = 0
        self.hits = 0
        self.lock = threading.Lock()

    def __call__(self, scene, beams, *, seed, threads=None, **kwargs):
        key = (id(scene), _digest(beams, seed, kwargs))
        with self.lock:
            entry = self.entries.get(key)
            if entry is not None and entry[0]() is scene:
                self.entries.move_to_end(key)
                self.hits += 1
                return entry[1]
        res = trace(scene, beams, seed=seed, threads=threads, **kwargs)
        with self.lock:
            old = self.entries.pop(key, None)  # a scene of the same id that is gone, or a twin thread's
            if old is not None:
                self.bytes -= old[1].sigma.nbytes
            self.entries[key] = (weakref.ref(scene), res)
            self.bytes += res.sigma.nbytes
            while len(self.entries) > 1 and self.bytes > self.max_bytes:
                _, (_, dropped) = self.entries.popitem(last=False)
                self.bytes -= dropped.sigma.nbytes
        return res


def sigma_effects(effects: dict) -> tuple:
    """The effects of ``effects`` that change sigma(t) (all but the sensor's), off values dropped:
    two models with equal ones trace the same sigma(t) from the same seed."""
    veg, mcrt, _, xy = split_effects(effects)
    on = {**veg, **mcrt, "xy_error": xy}
    return tuple(sorted((k, v) for k, v in on.items() if v != CATALOGUE[k].off))


def _echo_stem_distance(pulses: pa.Table, feats: pd.DataFrame) -> np.ndarray:
    """Horizontal distance (m) from the stem of each feature row's first echo, on the beam of its
    row of ``pulses`` (matched by pulse_id; :func:`.strata.stem_distance`)."""
    ids = pulses.column("pulse_id").to_numpy()
    order = np.argsort(ids)
    rows = pulses.take(pa.array(order[np.searchsorted(ids, feats["pulse_id"].to_numpy(np.int64), sorter=order)]))
    return stem_distance(rows, feats["echo_z"].to_numpy(float))


class StudySimulator:
    """``simulate(pulses, effects, seed) -> feature table`` over the study's real chain.

    Parameters
    ----------
    selected : dict
        Dataset -> ``select`` pulse table (pa.Table) of that dataset.
    datasets : DataFrame
        The campaign's datasets.csv (:func:`waveforest.io.tables.read_datasets`).
    calibrations : dict
        Dataset -> (Calibration of :mod:`waveforest.sensor.calibration`, calibration JSON dict).
    settings : DiagnoseSettings
        The study's simulation chain (``simulate``), the base model's effects under every
        call's ``effects`` (``base_effects``), the rules (``strata``) and
        ``range_correction`` (the calibration's CFD range correction on the features' own
        CFD echoes, as in the ``features`` stage).
    threads : int, optional
        Threads of each MCRT call.
    calibration_pulses : dict, optional
        Dataset -> :class:`waveforest.model.calibration_pulses.CalibrationPulses`, to recalibrate
        S(t) under the sensor effects tried (module docstring).
    """

    def __init__(self, selected: dict, datasets: pd.DataFrame, calibrations: dict, settings: DiagnoseSettings, *,
                 threads: int | None = None, calibration_pulses: dict | None = None):

        self.selected = selected
        self.info = {ds: dataset_row(datasets, ds) for ds in selected}
        missing = sorted(set(selected) - set(calibrations))
        if missing:
            raise WaveforestError(f"diagnose: no calibration for dataset(s) {', '.join(missing)}")
        self.calibrations = calibrations
        self.simulate = settings.simulate
        self.strata = settings.strata
        self.base_effects = dict(settings.base_effects)
        self.range_correction = bool(settings.range_correction)
        self.threads = threads
        self.scenes = SceneCache(base_effects=self.base_effects)
        self.traces = TraceCache()
        self.pulses_simulated = 0
        self.calibration_pulses = dict(calibration_pulses or {})
        self.recalibrated: dict = {}

    def calibration(self, dataset: str, effects: dict) -> tuple:
        """(Calibration, calibration JSON) of ``dataset`` for a model with ``effects`` (all of them).

        The calibrate stage's own when the calibration-shaping sensor effects are those of the
        base model or no target pulses were given; else S(t) recalibrated under them.
        """

        wanted = calibration_effects(effects)
        if wanted == calibration_effects(self.base_effects) or dataset not in self.calibration_pulses:
            return self.calibrations[dataset]
        key = (dataset, tuple(sorted(wanted.items())))
        if key not in self.recalibrated:
            cal, meta = self.calibrations[dataset]
            system = self.calibration_pulses[dataset].system_waveform(wanted)
            self.recalibrated[key] = (replace(cal, system=system), {**meta, "fwhm_ns": system.fwhm_ns})
        return self.recalibrated[key]

    def _features(self, sub: pa.Table, ds: str, model: dict, simulate: SimulateSettings,
                  stream: int = 0) -> pd.DataFrame | None:
        """Feature table of the twins of the rows of ``sub`` (one dataset); None when none has an echo."""

        cal, meta = self.calibration(ds, model)
        base_sigma = sigma_effects(model) == sigma_effects(self.base_effects)
        sim, _ = simulate_pulses(sub, self.info[ds], cal, simulate, effects=model, progress=False,
                                 threads=self.threads, scene_builder=self.scenes, stream=stream,
                                 tracer=self.traces if base_sigma else None)
        self.pulses_simulated += sub.num_rows
        if sim.num_rows == 0:
            return None
        rc = {ds: range_correction_of(meta)} if self.range_correction else None
        # the gap reads first-echo features and the waveform statistics: no decomposition of the twins
        feats = feature_table(sim, {ds: meta}, replace(simulate.sensor.features, decomposition=False),
                              cfd=cal.cfd or simulate.sensor.cfd, range_corrections=rc)
        stats = waveform_statistics(sim, {ds: meta}, feats[["echo_z"]])
        for f in WAVEFORM_FEATURES:
            feats[f] = stats[f].to_numpy()
        return feats

    def _below_crown(self, sub: pa.Table, ds: str, model: dict, simulate: SimulateSettings) -> list[pd.DataFrame]:
        """Twins of the pulses under the crowns: for each, the first of up to
        :data:`BELOW_CROWN_ATTEMPTS` attempts whose first echo meets ``select``'s rule for the
        stratum (lower than ``select.tree_min_echo_h_m``, within ``select.tree_radius_m`` of the
        stem on the recorded beam line); attempt k > 0 turns the beam about the stem by a seeded
        azimuth (:func:`turned_about_stems`) and draws rays, noise and offsets anew (random
        stream k) over the same plant."""

        low, radius = float(self.strata.rules.tree_min_echo_h_m), float(self.strata.rules.tree_radius_m)
        found = []
        for k in range(BELOW_CROWN_ATTEMPTS):
            if sub.num_rows == 0:
                break
            ids = sub.column("pulse_id").to_numpy()
            turned = sub if k == 0 else turned_about_stems(
                sub, hash_ids(stable_hash(int(simulate.seed), ds, "azimuth", k), ids) / 2.0**64 * 2.0 * np.pi)
            feats = self._features(turned, ds, model, simulate, stream=k)
            if feats is None:
                continue
            under = (feats["H"].to_numpy(float) < low) & (_echo_stem_distance(turned, feats) <= radius)
            found.append(feats[under])
            sub = sub.filter(pa.array(~np.isin(ids, feats["pulse_id"].to_numpy(np.int64)[under])))
        return found

    def _ring(self, sub: pa.Table, ds: str, model: dict, simulate: SimulateSettings) -> list[pd.DataFrame]:
        """Twins of the ring's pulses whose own first echo lies beyond ``select.tree_radius_m``
        of the stem (the rule that kept their real pulses out of the samples)."""

        feats = self._features(sub, ds, model, simulate)
        if feats is None:
            return []
        return [feats[_echo_stem_distance(sub, feats) > float(self.strata.rules.tree_radius_m)]]

    def __call__(self, pulses: pd.DataFrame, effects: dict, seed: int) -> pd.DataFrame:
        """Simulate the rows of ``pulses`` (dataset, pulse_id) under ``effects``.

        Returns
        -------
        DataFrame
            Feature table of the simulated pulses (dataset, pulse_id, sample_id, species,
            is_tree, H, Npeaks, Apeak, FWHM, E, n_echoes, ...), selection rules applied.
        """
        simulate = replace(self.simulate, seed=int(seed) % 2**63)
        model = {**self.base_effects, **effects}
        self.scenes.new_pass()
        parts = []
        for ds, rows in pulses.groupby("dataset", sort=True):
            if ds not in self.selected:
                raise WaveforestError(f"diagnose: no select table for dataset {ds}")
            table = self.selected[ds]
            stratum = rows["stratum"] if "stratum" in rows else pd.Series("", index=rows.index)
            ids = rows["pulse_id"].to_numpy(np.int64)
            sub = table.filter(pc.is_in(table.column("pulse_id"), value_set=pa.array(ids)))
            sub = sub.set_column(sub.schema.get_field_index("comparison_set"), "comparison_set",
                                 pa.array(np.ones(sub.num_rows, bool)))
            have = sub.column("pulse_id").to_numpy()
            under, ring = (np.isin(have, rows.loc[stratum == name, "pulse_id"].to_numpy(np.int64))
                           for name in (BELOW_CROWN, RING))
            plain = ~under & ~ring
            feats = [self._features(sub.filter(pa.array(plain)), ds, model, simulate)] if plain.any() else []
            feats += self._below_crown(sub.filter(pa.array(under)), ds, model, simulate) if under.any() else []
            feats += self._ring(sub.filter(pa.array(ring)), ds, model, simulate) if ring.any() else []
            feats = [f for f in feats if f is not None]
            if not feats:
                continue
            feats = pd.concat(feats, ignore_index=True)
            if "stratum" in rows.columns:  # the twin is in its real pulse's stratum (apply_rules)
                feats = feats.merge(rows[["pulse_id", "stratum"]], on="pulse_id", how="left", validate="one_to_one")
            parts.append(feats)
        if not parts:
            raise WaveforestError("diagnose: the simulation produced no pulse with an echo")
        return apply_rules(pd.concat(parts, ignore_index=True), self.strata)
