"""Simulate the selected real pulses of the modelled species (docs/method.md §(i1)).

For each selected pulse of ``simulate.species`` (``select``'s ``comparison_set``): a
vegetation instance of the species at the sample's field height, placed at the sample's
GNSS position (scene origin = (sample_x, sample_y, ground_z)); a beam with the real pulse's
sensor position and direction and the dataset's divergence (footprint = divergence x R);
MCRT (config ``mcrt``); the sensor model with the dataset's calibrated S(t) and noise at the
dataset's sampling; the CFD. The result is a pulse table (``source = sim``) with the real
pulse's ``pulse_id``, geometry and sample columns, the simulated waveform, its CFD echoes
(times from the first sample; positions on the recorded beam line), and ``sim_instance``,
``sigma_total``, ``mcrt_rays`` (the rays the pulse was traced with: the adaptive budget of
``mcrt.tolerance`` at the dataset's calibrated S(t), noise and the pulse's R and AGC gain).

R of Eq. 7 is the pulse's range to the sample's ground plane along the beam (docs/method.md §(c)).

Each twin is recorded at the AGC gain g of its real pulse (``agc_gain``, Eq. 1) and
AGC-normalised like it (:func:`waveforest.model.forward.render_sigma`): the simulated waveform
is in the AGC-normalised DN of the real one, with the real one's noise SD (noise_sd / g: the
AGC gains the signal, not the noise) and rounding steps (1/g DN); a ``nonlinearity`` effect
(detector saturation at L DN) acts on the gained signal, as in the sensor. Why this matters
(twins at gain 1 had fewer noise peaks): docs/validation.md ("AGC gain of birch crown pulses").

Vegetation instances: the paper builds a new instance for every pulse. Here each field
sample has a pool of ``simulate.instances_per_sample`` instances (seeded by the master seed,
the sample and the instance number, so every dataset of a year sees the same plants) and
each pulse is assigned one of them by a seeded hash. This is statistically sound: every
pulse still sees an independent-in-distribution draw from the vegetation model, so means and
SDs of the features estimate the same quantities; only pulses sharing an instance are
correlated -- which is also true of the real pulses, which all hit the same real plant.
``instances_per_sample: null`` gives the paper's rule (one instance per pulse). Pulses that
share an instance are traced in one batched MCRT call.

Chunks (the ``{chunk}`` wildcard): the unit of work is one (sample, instance) group; it goes to
chunk ``hash(dataset, sample_id, instance) % chunks``. All random numbers of a group
(scene, MCRT, sampling phase, noise) derive from the master seed, the dataset, the sample and
the instance, never from the chunk, so the union of the chunks is identical for any number
of chunks.

Effects (src/waveforest/effects.py) go to the module that applies them: vegetation effects to
``build_scene``, mcrt effects to ``trace``, sensor effects to ``render``; ``xy_error`` shifts
each traced beam horizontally by a georeferencing drift of SD xy_error per axis, correlated in
GPS time (:func:`waveforest.model.forward.georeferencing_drift`: the pulses of one pass over a
sample share nearly one offset), while the pulse keeps its recorded coordinates (the truth
differs from the record).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
import pyarrow as pa

from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError
from waveforest.io.pulses import PULSE_SCHEMA, padded_to_list
from waveforest.io.tables import divergence_mrad
from waveforest.mcrt import Beams, trace
from waveforest.mcrt.threads import default_threads
from waveforest.model.forward import (
    MCRTSetup,
    SensorSettings,
    SensorSetup,
    georeferencing_drift,
    split_effects,
    trace_and_render,
)
from waveforest.rng import child_seed63, hash_ids, hashed_seed63, hashed_sequence, sequence_generator, stable_hash
from waveforest.sensor.agc import GAIN_COLUMN
from waveforest.sensor.calibration import Calibration
from waveforest.sensor.checks import gain_or_one
from waveforest.vegetation import build_scene
from waveforest.workers import unordered_map

_SIM_FIELDS = [pa.field("sim_instance", pa.int64()), pa.field("sigma_total", pa.float64()),
               pa.field("mcrt_rays", pa.int64())]
"""Fields a simulated pulse table has after the pulse schema and the carried select columns."""

_CARRY = ("sample_id", "species", "functional_group", "ground_z", "sample_x", "sample_y", "height_m",
          "is_tree", "classification_set", "comparison_set")
"""select columns copied from the real pulse to its simulated twin."""

_SCALARS = ["dataset", "pulse_id", "gps_time", "sensor_x", "sensor_y", "sensor_z", "dir_x", "dir_y", "dir_z",
            "anchor_x", "anchor_y", "anchor_z", "range_m", "scan_angle_deg", "n_echoes"]


_REQUIRED = ("sample_id", "species", "ground_z", "sample_x", "sample_y", "height_m", "comparison_set")
"""select columns without which no pulse can be simulated."""



@dataclass(frozen=True)
class SimulateSettings:
    """The simulation chain of the config (built by :func:`waveforest.settings.simulate_settings`);
    ``seed`` (int) is the master seed of every random number of the chain.

    Attributes
    ----------
    species : tuple of str
        Modelled species (``simulate.species``).
    max_pulses : int or None
        At most this many pulses per species and dataset (seeded rank); None: all.
    instances_per_sample : int or None
        Vegetation instances per field sample; None: one per pulse.
    effects : mapping name -> value
        Effects of the model (src/waveforest/effects.py); a call's ``effects`` replaces them.
    ground_rho : float
        Ground reflectance of the scenes.
    lai_jitter : float
        Relative SD of the instances' leaf area.
    mcrt : MCRTSetup
        The tracer (its effects are replaced by the chain's mcrt effects).
    sensor : SensorSettings
        The sensor model, completed by each dataset's calibration and sampling.
    """

    seed: int
    species: tuple[str, ...]
    max_pulses: int | None
    instances_per_sample: int | None
    effects: Mapping[str, float]
    ground_rho: float
    lai_jitter: float
    mcrt: MCRTSetup
    sensor: SensorSettings


def plan(selected: pd.DataFrame, settings: SimulateSettings, dataset: str) -> pd.DataFrame:
    """Which selected pulses are simulated, with which instance, in which chunk.

    Parameters
    ----------
    selected : DataFrame
        Scalar columns of the select table (pulse_id, species, sample_id, comparison_set, ...).
    settings : SimulateSettings
        seed, species, max_pulses and instances_per_sample are used.
    dataset : str

    Returns
    -------
    DataFrame (index = row of ``selected``) with columns pulse_id, species, sample_id,
    instance (int64), group (str) and chunk_hash (int64 in [0, 2^32); chunk = chunk_hash % chunks).
    """
    seed = int(settings.seed)
    rows = selected[selected["comparison_set"].astype(bool) & selected["species"].isin(list(settings.species))]
    rows = rows[["pulse_id", "species", "sample_id"]].copy()
    rows["_rank"] = hash_ids(stable_hash(seed, dataset, "order"), rows["pulse_id"].to_numpy(np.int64))
    cap = settings.max_pulses
    if cap is not None:
        rows = rows.sort_values(["_rank", "pulse_id"]).groupby("species", sort=False).head(int(cap))
    k = settings.instances_per_sample
    if k is None:
        inst = rows["pulse_id"].to_numpy(np.int64)
    else:
        inst = (hash_ids(stable_hash(seed, dataset, "instance"), rows["pulse_id"].to_numpy(np.int64))
                % np.uint64(int(k))).astype(np.int64)
    rows["instance"] = inst
    rows["group"] = rows["sample_id"].astype(str) + "#" + rows["instance"].astype(str)
    codes = {s: stable_hash(dataset, s) for s in rows["sample_id"].astype(str).unique()}
    sample_code = rows["sample_id"].astype(str).map(codes).to_numpy(np.int64)
    mixed = hash_ids(stable_hash("chunk"), sample_code) ^ rows["instance"].to_numpy(np.int64).astype(np.uint64)
    rows["chunk_hash"] = (hash_ids(0, mixed.view(np.int64)) % np.uint64(2**32)).astype(np.int64)
    return rows.drop(columns="_rank").sort_index()


def beam_geometry(rows: Mapping) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensor positions, unit directions and R (range to the sample's ground plane).

    ``rows``: a DataFrame or a mapping of column name -> (n,) array (sensor_x/y/z, dir_x/y/z,
    ground_z). Pulses without a sensor position (ingested without a trajectory) get NaN rows
    and are not simulated.

    Returns
    -------
    sensor : (n, 3) float64, m (world coordinates; NaN rows cannot be simulated)
    direction : (n, 3) float64, unit
    range_m : (n,) float64, m
    """
    sensor = np.column_stack([np.asarray(rows[c], float) for c in ("sensor_x", "sensor_y", "sensor_z")])
    d = np.column_stack([np.asarray(rows[c], float) for c in ("dir_x", "dir_y", "dir_z")])
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    down = -d[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = (sensor[:, 2] - np.asarray(rows["ground_z"], float)) / down
    r = np.where(down > 0, r, np.nan)
    return sensor, d, r


@dataclass(frozen=True)
class SimulateSummary:
    """What :func:`run` wrote."""

    dataset: str
    chunk: int
    n_pulses: int
    n_written: int
    n_instances: int
    n_no_echo: int



def simulate_pulses(selected: pa.Table, dataset_info: pd.Series, calibration: Calibration,
                    settings: SimulateSettings, *, chunk: int = 0, chunks: int = 1, effects: dict | None = None,
                    progress: bool = True, threads: int | None = None, scene_builder=None, stream: int = 0,
                    tracer=None) -> tuple[pa.Table, SimulateSummary]:
    """Simulate the pulses of ``selected`` that fall into ``chunk`` (see module docstring).

    Parameters
    ----------
    selected : pa.Table
        ``select`` output of one dataset.
    dataset_info : Series
        The dataset's row of datasets.csv (sampling_ns, divergence_mrad or footprint/range).
    calibration : Calibration
    settings : SimulateSettings
    chunk, chunks : int
    effects : dict name -> value, optional (default ``settings.effects``)
    progress : bool
        tqdm bar over the chunk's pulses (stderr).
    threads : int, optional
        Worker threads (default: Numba's thread count); with more than one, the (sample,
        instance) groups are shared over them, each built and traced serially
        (:func:`waveforest.workers.unordered_map`), so that builds overlap with tracing.
        The table does not depend on it.
    scene_builder : callable, optional
        ``f(species, height, seed, **kwargs) -> Scene``; default
        :func:`waveforest.vegetation.build_scene`.
    stream : int
        0: the study's random numbers; k > 0: an independent draw of the rays, noise,
        sampling phase and ``xy_error`` offsets over the same plants.
    tracer : callable, optional
        :func:`waveforest.mcrt.trace` (default) or a stand-in with its signature and results.

    Returns
    -------
    (pa.Table, SimulateSummary)
        The simulated pulse table (PULSE_SCHEMA + select columns + sim_instance, sigma_total).
    """
    if not 0 <= chunk < chunks:
        raise WaveforestError(f"chunk {chunk}: expected 0 <= chunk < chunks = {chunks}")
    dataset = str(dataset_info["dataset"])
    fx = split_effects(dict(settings.effects if effects is None else effects))
    scal, carry = _scalars(selected, dataset)
    p = plan(scal, settings, dataset)
    p = p[(p["chunk_hash"] % chunks) == chunk]
    workers = threads if threads is not None else default_threads()
    chain = _chain(settings, dataset_info, calibration, fx, scene_builder or build_scene,
                   1 if workers > 1 else threads, stream, tracer or trace)
    rows = _Rows({c: scal[c].to_numpy() for c in scal.columns}, selected.select(carry.names))
    groups = _groups(p)
    pieces, n_no_echo = _run_groups(chain, rows, groups, workers,
                                    f"simulate {dataset} chunk {chunk}" if progress else None)
    table = pa.concat_tables(pieces) if pieces else _empty(carry)
    summary = SimulateSummary(dataset, chunk, int(len(p)), table.num_rows, len(groups), n_no_echo)
    return table, summary


def _scalars(selected: pa.Table, dataset: str) -> tuple[pd.DataFrame, pa.Schema]:
    """The scalar columns of a select table (DataFrame) and the schema of its carried select columns."""
    missing = [c for c in _REQUIRED if c not in selected.column_names]
    if missing:
        raise WaveforestError(f"select table of {dataset} lacks column(s) {', '.join(missing)}")
    scal = selected.select([c for c in _SCALARS + [GAIN_COLUMN] + list(_CARRY)
                            if c in selected.column_names]).to_pandas()
    carry = pa.schema([selected.schema.field(c) for c in _CARRY if c in selected.column_names])
    return scal, carry


@dataclass(frozen=True)
class _Rows:
    """A select table's scalar columns as NumPy arrays (``cols``, row i = the table's row i) and
    its carried columns (``carry``, Arrow): what the groups take their rows from, without a
    DataFrame per group."""

    cols: dict
    carry: pa.Table

    def take(self, pos: np.ndarray) -> dict:
        """Column name -> the values at rows ``pos``."""
        return {k: v[pos] for k, v in self.cols.items()}


def _groups(p: pd.DataFrame) -> list[tuple[np.ndarray, int]]:
    """The (sample, instance) groups of plan ``p`` in the order of their names: (rows of the
    select table in pulse_id order, instance)."""
    codes, _ = pd.factorize(p["group"], sort=True)
    order = np.lexsort((p["pulse_id"].to_numpy(np.int64), codes))
    pos, inst = p.index.to_numpy(np.int64)[order], p["instance"].to_numpy(np.int64)[order]
    cuts = np.flatnonzero(np.diff(codes[order])) + 1
    return [(r, int(inst[r0])) for r, r0 in zip(np.split(pos, cuts), np.r_[0, cuts])] if len(pos) else []


@dataclass(frozen=True)
class _Chain:
    """Everything a (sample, instance) group of one dataset needs, but its pulses."""

    seed: int
    dataset: str
    scene_builder: Callable
    vegetation: dict
    ground_rho: float
    lai_jitter: float
    divergence_mrad: float
    xy_error: float
    mcrt: MCRTSetup
    setup: SensorSetup
    threads: int | None
    stream: int
    tracer: Callable

    def group(self, rows: _Rows, group: tuple[np.ndarray, int]) -> tuple[pa.Table | None, int]:
        """The twins of one group (:func:`_groups`): scene, seeds, :func:`_simulate_group`."""
        pos, inst = group
        first = pos[0]
        sample_id = str(rows.cols["sample_id"][first])
        scene = self.scene_builder(str(rows.cols["species"][first]), float(rows.cols["height_m"][first]),
                                   hashed_seed63(self.seed, "scene", sample_id, inst),
                                   ground_rho=self.ground_rho, lai_jitter=self.lai_jitter, **self.vegetation)
        ss = hashed_sequence(self.seed, self.dataset, "pulses", sample_id, inst,
                             *((int(self.stream),) if self.stream else ()))
        return _simulate_group(rows, pos, scene, ss, inst, self.divergence_mrad, self.xy_error, self.mcrt,
                               self.setup, self.threads, self.tracer)


def _chain(settings: SimulateSettings, dataset_info: pd.Series, calibration: Calibration, effects: tuple,
           scene_builder, threads: int | None, stream: int, tracer: Callable) -> _Chain:
    """The chain of one dataset: the calibrated sensor, the tracer and ``effects`` as
    :func:`.forward.split_effects` splits them."""
    veg_fx, mcrt_fx, sensor_fx, xy_error = effects
    setup = settings.sensor.setup(calibration.system, calibration.noise_mean, calibration.noise_sd,
                                  float(dataset_info["sampling_ns"]), sensor_fx, calibration.range_correction,
                                  calibration.cfd)
    return _Chain(seed=int(settings.seed), dataset=str(dataset_info["dataset"]), scene_builder=scene_builder,
                  vegetation=veg_fx, ground_rho=float(settings.ground_rho), lai_jitter=float(settings.lai_jitter),
                  divergence_mrad=divergence_mrad(dataset_info), xy_error=xy_error,
                  mcrt=replace(settings.mcrt, effects=mcrt_fx), setup=setup, threads=threads,
                  stream=int(stream), tracer=tracer)


def _run_groups(chain: _Chain, rows: _Rows, groups: list[tuple[np.ndarray, int]], workers: int,
                desc: str | None) -> tuple[list[pa.Table], int]:
    """The groups' sim tables in group order over ``workers`` threads, and the pulses lost
    (no geometry or no simulated echo); ``desc``: a tqdm bar's label (None: no bar)."""
    bar = None
    if desc is not None:
        from tqdm import tqdm

        bar = tqdm(total=sum(len(g[0]) for g in groups), desc=desc, unit="pulse", leave=False)
    done: dict[int, pa.Table] = {}
    n_lost = 0
    for i, (piece, lost) in unordered_map(lambda g: chain.group(rows, g), groups, workers):
        n_lost += lost
        if piece is not None:
            done[i] = piece
        if bar is not None:
            bar.update(len(groups[i][0]))
    if bar is not None:
        bar.close()
    return [done[i] for i in sorted(done)], n_lost


def _simulate_group(rows: _Rows, pos: np.ndarray, scene, ss: np.random.SeedSequence, inst: int, div,
                    xy_error: float, mcrt: MCRTSetup, setup: SensorSetup, threads,
                    tracer: Callable) -> tuple[pa.Table | None, int]:
    """The twins of one (sample, instance) group, the select rows ``pos``: beams, MCRT, Eq. 7 at
    each pulse's AGC gain, CFD.

    ``ss`` seeds the group: its first spawned child gives the MCRT seed (63 bits), ``ss`` itself
    the ``xy_error`` offsets, then the sampling phase and noise. Returns (sim rows or None, the
    number of pulses without geometry or without a simulated echo).
    """
    d = rows.take(pos)
    sensor, direction, r = beam_geometry(d)
    ok = np.all(np.isfinite(sensor), axis=1) & np.isfinite(r) & (r > 0)
    lost = int((~ok).sum())
    if not ok.any():
        return None, lost
    sensor, direction, r, pos = sensor[ok], direction[ok], r[ok], pos[ok]
    d = {k: v[ok] for k, v in d.items()}
    trace_seed = child_seed63(ss)
    rng = sequence_generator(ss)
    offset = np.zeros_like(sensor)
    if xy_error > 0:
        offset[:, :2] = xy_error * georeferencing_drift(rng.standard_normal((len(pos), 2)),
                                                        d["gps_time"].astype(float))
    origin = sensor - np.column_stack([d["sample_x"], d["sample_y"], d["ground_z"]]).astype(float) + offset
    beams = Beams.from_divergence(origin, direction, div, r)
    gain = gain_or_one(d[GAIN_COLUMN].astype(float)) if GAIN_COLUMN in d else np.ones(len(pos))
    sim, _ = trace_and_render(scene, beams, r, mcrt, setup, trace_seed, rng, threads, gain=gain, tracer=tracer)
    keep = sim.n_echoes > 0
    lost += int((~keep).sum())
    if not keep.any():
        return None, lost
    d = {k: v[keep] for k, v in d.items()}
    return _table(d, rows.carry.take(pos[keep]), sensor[keep], direction[keep], sim, keep, inst), lost


def _table(d: Mapping, carried: pa.Table, sensor, direction, sim, keep, inst: int) -> pa.Table:
    """The sim pulse rows of one batch (only rows ``keep`` of ``sim``; ``d``, ``carried``,
    ``sensor`` and ``direction`` hold those rows only)."""
    n = int(keep.sum())
    first = sim.first_sample_ns[keep]
    times = sim.echo_times_ns[keep]
    amps = sim.echo_amplitudes[keep]
    counts = sim.n_echoes[keep].astype(np.int64)
    anchor = sensor + direction * (first * RANGE_PER_NS)[:, None]
    ranges = (first[:, None] + times) * RANGE_PER_NS
    echo = sensor[:, None, :] + direction[:, None, :] * ranges[:, :, None]  # (n, 4, 3)
    samples = sim.samples[keep]
    lengths = sim.lengths[keep]
    cols = {
        "dataset": pa.array(d["dataset"].astype(str), pa.string()),
        "pulse_id": pa.array(d["pulse_id"].astype(np.int64)),
        "source": pa.array(["sim"] * n, pa.string()),
        "gps_time": pa.array(d["gps_time"].astype(float)),
        "sensor_x": sensor[:, 0], "sensor_y": sensor[:, 1], "sensor_z": sensor[:, 2],
        "dir_x": direction[:, 0], "dir_y": direction[:, 1], "dir_z": direction[:, 2],
        "anchor_x": anchor[:, 0], "anchor_y": anchor[:, 1], "anchor_z": anchor[:, 2],
        "range_m": ranges[:, 0],
        "scan_angle_deg": d["scan_angle_deg"].astype(float),
        "agc": np.full(n, np.nan), "sampling_ns": np.full(n, sim.sampling_ns),
        "digitizer_gain": np.full(n, np.nan), "digitizer_offset": np.full(n, np.nan),
        "samples": padded_to_list(samples, lengths, pa.float32()),
        "n_echoes": pa.array(counts.astype(np.int16), pa.int16()),
        "echo_x": padded_to_list(echo[:, :, 0], counts, pa.float64()),
        "echo_y": padded_to_list(echo[:, :, 1], counts, pa.float64()),
        "echo_z": padded_to_list(echo[:, :, 2], counts, pa.float64()),
        "echo_time_ns": padded_to_list(times, counts, pa.float64()),
        "echo_intensity": padded_to_list(amps.astype(np.float32), counts, pa.float32()),
    }
    arrays = [cols[f.name] if isinstance(cols[f.name], (pa.Array, pa.ChunkedArray)) else pa.array(cols[f.name], f.type)
              for f in PULSE_SCHEMA]
    rays = np.zeros(len(keep), np.int64) if sim.rays is None else sim.rays
    arrays += [carried.column(c).combine_chunks() for c in carried.column_names]
    arrays += [pa.array(np.full(n, inst, dtype=np.int64)), pa.array(sim.sigma_total[keep].astype(float)),
               pa.array(rays[keep].astype(np.int64))]
    return pa.Table.from_arrays(arrays, schema=pa.schema(list(PULSE_SCHEMA) + list(carried.schema) + _SIM_FIELDS))


def _empty(carry: pa.Schema) -> pa.Table:
    """An empty sim table with the full set of columns."""
    return pa.Table.from_pylist([], schema=pa.schema(list(PULSE_SCHEMA) + list(carry) + _SIM_FIELDS))


def with_sample_columns(selected: pa.Table, fields: pd.DataFrame, source: str = "fields.csv") -> pa.Table:
    """Add sample_x, sample_y and height_m from ``fields`` to a select table that lacks them."""
    need = [c for c in ("sample_x", "sample_y", "height_m") if c not in selected.column_names]
    if not need or "sample_id" not in selected.column_names:
        return selected
    f = fields.set_index(fields["sample_id"].astype(str))
    ids = pd.Series(selected.column("sample_id").to_pylist(), dtype=object).astype(str)
    missing = sorted(set(ids) - set(f.index))
    if missing:
        raise WaveforestError(f"{source}: sample_id {missing[0]!r} of the select table is not listed")
    src = {"sample_x": "x", "sample_y": "y", "height_m": "height_m"}
    for c in need:
        selected = selected.append_column(c, pa.array(f.loc[ids, src[c]].to_numpy(float), pa.float64()))
    return selected
