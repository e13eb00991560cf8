"""Fly a survey: tiles of pulses traced with multiple scattering, rendered by the sensor twin.

Pulses are grouped in square tiles (``quality.tile_m``) by where their axis crosses the
scene's lowest level. One tile is one unit of work (a chunk): its scene is the static
triangles and plant copies whose boxes overlap the tile plus a margin (half the viewed
diameter, the horizontal reach of the most oblique beam through the scene's height, 1 m), one BVH
(plants as Embree instances of their prototypes), all its pulses traced in batched calls of
``output.chunk_pulses`` and then freed, so memory does not grow with the survey. Each tile's
pulse table is kept as a Parquet file in a cache folder beside the output; an interrupted run
resumes from the tiles already there, and :func:`merge` streams them into the LAS file.

Radiometry (docs/method.md Eq. 7): waveform = S(t) * sigma(t) / R(t)^2 with R(t) = c t / 2 the
range of each sigma bin (:func:`at_range`: relief and tall objects under a survey lie at ranges
far apart); a Gaussian S(t) is scaled so that a nadir
Lambertian plane of HDRF ``plane_hdrf`` at 1200 m peaks at ``plane_dn`` DN (times ``gain``),
and its CFD time is the echo time, so a planar target's discrete return is at its range.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.atomic import atomic_path
from waveforest.constants import C_M_PER_NS, RANGE_PER_NS
from waveforest.io.pulses import padded_to_list
from waveforest.mcrt import Beams, Prototypes, prepare, prepare_instances, prepare_prototypes, trace
from waveforest.mcrt.tracer import T0_LEAD_NS, bvh_quality
from waveforest.model.forward import MCRTSetup, SensorSettings, SensorSetup, SimPulses, render_sigma
from waveforest.rng import named_generator
from waveforest.sensor import CFDParams, gaussian_system_waveform, load_system_waveform
from waveforest.survey.scan import Pulses, axis_hits_box, concat, fly_blocks, leg_tracks
from waveforest.survey.scene import SurveyScene
from waveforest.survey.spec import Survey, SurveyError

REFERENCE_RANGE_M = 1200.0
"""Range at which the preset's reference plane peaks at ``plane_dn`` DN."""

MULTIPLE_SCATTERING_NS = 40.0
"""sigma window beyond the tile box's depth along the beam, ns (late multiple scattering: what
arrives later is not recorded, and ``summary.json`` gives its share, ``sigma_after_window``)."""

FIRST_ORDER_MARGIN_NS = 2.0
"""sigma window beyond the box's depth along the beam at first order only, ns (the tracer's
start-plane margin and the footprint's spread)."""

DATASET = "survey"


@dataclass(frozen=True)
class Plan:
    """The pulses that reach the scene, grouped by tile."""

    pulses: Pulses
    tile: np.ndarray           # (n,) int64 tile id of each pulse
    tiles: np.ndarray          # (k,) sorted tile ids
    tile_xy: np.ndarray        # (k, 2) tile lower-left corner, m
    ground_z: float
    n_flown: int
    tracks: list
    tile_m: float              # side of the tiles, m


ADAPTIVE_TILE_PULSES = 256
"""Under the adaptive ray budget, tiles are widened (:func:`tile_side`) until they hold this many
pulses on average: the budget's pulses differ in cost, and a tile ends when its slowest chunk
does, so a tile of few pulses leaves a thread idle (``CHUNKS_PER_WORKER`` x
``ADAPTIVE_CHUNK_PULSES`` x 2 threads = 256 pulses fill both threads' chunks)."""


def tile_side(tile_m: float, n_pulses: int, n_tiles: int, min_pulses: int) -> float:
    """``tile_m`` times the smallest integer f with f^2 x the mean pulses per tile >= ``min_pulses``
    (f = 1 when the tiles already hold that many)."""
    mean = n_pulses / max(n_tiles, 1)
    if mean <= 0 or mean >= min_pulses:
        return float(tile_m)
    return float(tile_m) * math.ceil(math.sqrt(min_pulses / mean))


def tile_ids(ground: np.ndarray, lo: np.ndarray, side: float) -> tuple[np.ndarray, np.ndarray]:
    """The tile id of each point ``ground`` (n, 2+) in tiles of ``side`` from ``lo`` (2,), and the sorted ids."""
    ij = np.floor((ground[:, :2] - lo) / side).astype(np.int64)
    tile = ij[:, 0] * 1_000_003 + ij[:, 1]
    return tile, np.unique(tile)


def plan(scene: SurveyScene, survey: Survey, min_tile_pulses: int = 1) -> Plan:
    """Fly the survey block by block; keep the pulses whose axis passes through the scene's box;
    tile them (memory: the kept pulses, about 80 bytes each). Tiles of side ``quality.tile_m``
    are widened by :func:`tile_side` to hold ``min_tile_pulses`` pulses on average.

    A leg none of whose pulses sees the scene, or a pulse fired from inside the scene's box
    (the tracer starts its rays at the box, so the sensor must be outside it), is an error
    naming the leg.
    """
    tracks = leg_tracks(survey)
    box = scene.bounds.copy()
    kept, seen, n_flown = [], np.zeros(len(tracks), bool), 0
    for block in fly_blocks(survey, tracks):
        n_flown += len(block)
        hit = axis_hits_box(block.origin, block.direction, box)
        seen[np.unique(block.leg[hit])] = True
        kept.append(block.take(np.flatnonzero(hit)))
    for leg in np.flatnonzero(~seen):
        where = "platform/trajectory" if survey.trajectory is not None else f"platform/legs/{leg}"
        lo, hi = box[0], box[1]
        raise SurveyError(f"{survey.source}: {where}: the leg sees no part of the scene (scene x {lo[0]:.1f}.."
                          f"{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f} m)")
    kept = concat(kept)
    inside = np.flatnonzero(np.all((kept.origin >= box[0]) & (kept.origin <= box[1]), axis=1))
    if inside.size:
        i = inside[np.argmin(kept.origin[inside, 2])]
        where = "platform/trajectory" if survey.trajectory is not None else f"platform/legs/{kept.leg[i]}"
        raise SurveyError(f"{survey.source}: {where}: the sensor flies inside the scene (z {kept.origin[i, 2]:.1f} m at "
                          f"GPS time {kept.gps_time[i]:.3f} s; the scene reaches z {box[1, 2]:.1f} m): "
                          "expected a flight above the scene")
    zg = float(box[0, 2])
    s = (zg - kept.origin[:, 2]) / kept.direction[:, 2]
    ground = kept.origin + s[:, None] * kept.direction
    side = float(survey.tile_m)
    tile, tiles = tile_ids(ground, box[0, :2], side)
    if min_tile_pulses > 1:  # the tiles of quality.tile_m, widened if they are too sparse
        side = tile_side(side, len(tile), len(tiles), min_tile_pulses)
        tile, tiles = tile_ids(ground, box[0, :2], side)
    tile_xy = box[0, :2] + side * np.stack([tiles // 1_000_003, tiles % 1_000_003], axis=1)
    order = np.lexsort((kept.gps_time, tile))
    return Plan(kept.take(order), tile[order], tiles, tile_xy, zg, n_flown, tracks, side)


def system_waveform(survey: Survey, cfd: CFDParams):
    """S(t) of the scanner: the calibrated one if given, else the scaled Gaussian (module docstring)."""
    sc = survey.scanner
    if sc.system_waveform is not None:
        return load_system_waveform(sc.system_waveform)
    peak = sc.gain * sc.plane_dn * math.pi * REFERENCE_RANGE_M**2 / sc.plane_hdrf
    return gaussian_system_waveform(sc.pulse_fwhm_ns, peak, cfd=cfd)


def survey_mcrt(mcrt: MCRTSetup, survey: Survey) -> MCRTSetup:
    """The config's tracer settings with the survey's ``quality`` where given: a fixed
    ``rays_per_pulse`` (no adaptive budget), else its ``tolerance`` or the config's; the highest order."""
    if survey.rays_per_pulse:
        mcrt = replace(mcrt, n_rays=int(survey.rays_per_pulse), tolerance=None)
    elif survey.tolerance is not None:
        mcrt = replace(mcrt, tolerance=float(survey.tolerance))
    return replace(mcrt, max_order=int(survey.max_order or mcrt.max_order))


RECORD_PAST_TRIGGER_FWHM = 2.0
"""A record must reach this many system-pulse FWHMs past the latest pre-trigger start."""


def sensor_setup(survey: Survey, sensor: SensorSettings) -> SensorSetup:
    """The sensor twin of the survey's scanner: the config's sensor model (pre-trigger, CFD
    delay and dead time, features) with the scanner's S(t), noise, sampling, bits, record
    length, CFD fraction and arming. A record too short to hold an echo past its pre-trigger
    is a :class:`SurveyError`."""
    sc = survey.scanner
    cfd = replace(sensor.cfd, fraction=float(sc.cfd_fraction), arming_sd=float(sc.cfd_arming_sd))
    settings = replace(sensor, record_ns=float(sc.record_ns), digitizer_max=2 ** int(sc.bits) - 1, cfd=cfd)
    setup = settings.setup(system_waveform(survey, cfd), sc.noise_mean, sc.noise_sd, sc.sampling_ns)
    lead = max(setup.pre_trigger_m) / RANGE_PER_NS
    need = lead + RECORD_PAST_TRIGGER_FWHM * setup.system.fwhm_ns
    if sc.record_ns < need:
        raise SurveyError(f"{survey.source}: scanner/record_ns: {sc.record_ns:g} ns cannot hold an echo: the record "
                          f"starts up to {lead:.1f} ns before the trigger (config sensor.pre_trigger_m); expected "
                          f"at least {need:.1f} ns (that and {RECORD_PAST_TRIGGER_FWHM:g} pulse widths)")
    return setup


def max_zenith_tan(pulses: Pulses) -> float:
    """The largest tangent of the beams' zenith angles (scan angle, roll and pitch together)."""
    d = pulses.direction
    return float((np.hypot(d[:, 0], d[:, 1]) / np.maximum(-d[:, 2], 1e-9)).max(initial=0.0))


class TileScenes:
    """Builds the scene of one tile (static triangles and plant copies overlapping its box)."""

    def __init__(self, scene: SurveyScene, survey: Survey, viewed_diameter_m: float, max_tan: float):
        """``max_tan``: the largest tangent of a pulse's zenith (:func:`max_zenith_tan`)."""
        self.scene = scene
        self.survey = survey
        dz = float(scene.bounds[1, 2] - scene.bounds[0, 2])
        self.margin = viewed_diameter_m / 2 + dz * float(max_tan) + 1.0
        if scene.static is not None:
            t = scene.static.triangles
            self.static_box = np.stack([t.min(axis=1), t.max(axis=1)], axis=1)
        self.protos: Prototypes | None = None
        if scene.plants is not None:
            self.protos = prepare_prototypes(list(scene.plants.prototypes))

    def build(self, xy: np.ndarray, n_pulses: int, n_rays: int, side: float | None = None):
        """The prepared scene of the tile with lower-left corner ``xy`` and side ``side`` (None:
        ``quality.tile_m``), or None if it is empty."""
        side = self.survey.tile_m if side is None else side
        lo = np.array([xy[0] - self.margin, xy[1] - self.margin, -np.inf])
        hi = np.array([xy[0] + side + self.margin, xy[1] + side + self.margin, np.inf])
        static = None
        if self.scene.static is not None:
            sel = np.all((self.static_box[:, 1] >= lo) & (self.static_box[:, 0] <= hi), axis=1)
            if sel.any():
                static = self.scene.static.subset(sel)
        plants = self.scene.plants
        copies = np.zeros(0, np.int64)
        if plants is not None:
            copies = np.flatnonzero(np.all((plants.box[:, 1] >= lo) & (plants.box[:, 0] <= hi), axis=1))
        if copies.size == 0:
            return None if static is None else _within(prepare(static, quality=bvh_quality(n_pulses, n_rays)), lo, hi)
        protos = self.protos
        which, rot, t = plants.which[copies], plants.rotation[copies], plants.translation[copies]
        if static is not None:  # the static part joins as one more prototype, placed as it is
            part = prepare(static, "embree", bvh_quality(n_pulses, n_rays))
            protos = Prototypes(protos.scenes + (part,), np.concatenate([protos.records, part.tri_data]),
                                np.append(protos.starts, protos.starts[-1] + len(part)))
            which = np.append(which, len(protos) - 1)
            rot = np.concatenate([rot, np.eye(3)[None]])
            t = np.concatenate([t, np.zeros((1, 3))])
        return _within(prepare_instances(protos, which, rot, t), lo, hi)


def _within(prepared, lo: np.ndarray, hi: np.ndarray):
    """``prepared`` with its box cut to [lo, hi] (world frame): the box that sets the tracer's
    start plane and the sigma window holds the tile's beams through the scene's heights, not a
    ground plane or mesh that reaches far beyond the tile (memory and time per pulse would grow
    with the scene's area)."""
    b = prepared.bounds + prepared.shift
    box = np.stack([np.maximum(b[0], lo), np.minimum(b[1], hi)])
    return replace(prepared, bounds=box - prepared.shift)


def window_ns(prepared, origin: np.ndarray, direction: np.ndarray, max_order: int = 10) -> float:
    """sigma window covering the prepared scene's box along every beam (the tracer starts it
    at the box's nearest corner), plus :data:`MULTIPLE_SCATTERING_NS` when orders above the
    first are traced, else :data:`FIRST_ORDER_MARGIN_NS` (a first-order path ends inside the box)."""
    b = prepared.bounds + prepared.shift
    corners = np.array([[b[i, 0], b[j, 1], b[k, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    depth = np.einsum("nck,nk->nc", corners[None] - origin[:, None], direction)
    span = float((depth.max(axis=1) - depth.min(axis=1)).max())
    return 2.0 * span / C_M_PER_NS + T0_LEAD_NS + (MULTIPLE_SCATTERING_NS if max_order > 1 else FIRST_ORDER_MARGIN_NS)


def pulse_table(p: Pulses, pulse_id: np.ndarray, sim, range_m: np.ndarray, agc: float = np.nan) -> pa.Table:
    """The pulses with at least one discrete return as a pulse table (io/pulses.py schema), each
    with AGC value ``agc`` (the scanner's :attr:`~waveforest.survey.spec.Scanner.agc`)."""
    keep = np.flatnonzero(sim.n_echoes > 0)
    d, o = p.direction[keep], p.origin[keep]
    first = sim.first_sample_ns[keep]
    anchor = o + d * (first * RANGE_PER_NS)[:, None]
    n_e = sim.n_echoes[keep].astype(np.int64)
    et = np.nan_to_num(sim.echo_times_ns[keep])
    exyz = anchor[:, None, :] + d[:, None, :] * (et * RANGE_PER_NS)[:, :, None]  # (k, 4, 3)
    n = len(keep)
    cols = {
        "dataset": pa.array([DATASET] * n), "pulse_id": pa.array(pulse_id[keep], pa.int64()),
        "source": pa.array(["sim"] * n), "gps_time": pa.array(p.gps_time[keep]),
        "sensor_x": pa.array(o[:, 0]), "sensor_y": pa.array(o[:, 1]), "sensor_z": pa.array(o[:, 2]),
        "dir_x": pa.array(d[:, 0]), "dir_y": pa.array(d[:, 1]), "dir_z": pa.array(d[:, 2]),
        "anchor_x": pa.array(anchor[:, 0]), "anchor_y": pa.array(anchor[:, 1]), "anchor_z": pa.array(anchor[:, 2]),
        "range_m": pa.array((first + et[:, 0]) * RANGE_PER_NS),
        "scan_angle_deg": pa.array(p.scan_angle_deg[keep]), "scan_flags": pa.array(p.scan_flags[keep], pa.uint8()),
        "point_source_id": pa.array(p.leg[keep] + 1, pa.uint16()),
        "agc": pa.array(np.full(n, float(agc))),
        "sampling_ns": pa.array(np.full(n, sim.sampling_ns)),
        "digitizer_gain": pa.array(np.ones(n)), "digitizer_offset": pa.array(np.zeros(n)),
        "samples": padded_to_list(sim.samples[keep], sim.lengths[keep], pa.float32()),
        "n_echoes": pa.array(n_e.astype(np.int16)),
        "echo_x": padded_to_list(exyz[:, :, 0], n_e, pa.float64()),
        "echo_y": padded_to_list(exyz[:, :, 1], n_e, pa.float64()),
        "echo_z": padded_to_list(exyz[:, :, 2], n_e, pa.float64()),
        "echo_time_ns": padded_to_list(et, n_e, pa.float64()),
        "echo_intensity": padded_to_list(np.nan_to_num(sim.echo_amplitudes[keep]), n_e, pa.float32()),
    }
    return pa.table(cols)


def truth_table(pulse_id: np.ndarray, gps_time: np.ndarray, res) -> pa.Table:
    """Per pulse (``gps_time`` joins it to the LAS points) sigma(t) by scattering order, trimmed
    to the bins between its first and last non-zero bin of any order (``t0_ns``: two-way time
    from emission of the first kept bin's left edge)."""
    by = res.sigma_by_order                                   # (n, orders, bins)
    nz = by.sum(axis=1) != 0                                  # (n, bins)
    any_ = nz.any(axis=1)
    a = np.where(any_, nz.argmax(axis=1), 0)
    b = np.where(any_, by.shape[2] - nz[:, ::-1].argmax(axis=1), 0)
    shifted = np.zeros_like(by)                               # each pulse's kept bins moved to the start
    j = np.arange(by.shape[2])
    src = np.minimum(a[:, None] + j[None, :], by.shape[2] - 1)
    for k in range(by.shape[1]):
        shifted[:, k] = np.take_along_axis(by[:, k], src, axis=1)
    table = {"pulse_id": pa.array(pulse_id, pa.int64()), "gps_time": pa.array(np.asarray(gps_time, np.float64)),
             "t0_ns": pa.array(res.t0_ns + a * res.bin_ns),
             "bin_ns": pa.array(np.full(len(pulse_id), res.bin_ns))}
    for k in range(by.shape[1]):
        table[f"sigma_order_{k + 1}"] = padded_to_list(shifted[:, k], b - a, pa.float64())
    return pa.table(table)


@dataclass
class TileResult:
    pulses: int = 0
    returns: int = 0
    recorded: int = 0
    """Pulses with a discrete return (the others have no point, hence no waveform, in the LAS)."""
    rays: int = 0
    cpu_s: float = 0.0
    saturated: int = 0
    """Pulses whose waveform reaches the digitiser's full scale (``setup.digitizer_max``)."""
    sigma: float = 0.0
    """Total sigma of the tile's pulses, all orders (sr^-1 per unit power)."""
    sigma_late: float = 0.0
    """The part of it that arrived after the sigma window (:func:`window_ns`), not recorded."""


def at_range(res, range_m: np.ndarray) -> np.ndarray:
    """sigma of a TraceResult with each bin's 1/R^2 referred to ``range_m`` (n,), m:
    sigma(t) (range_m / R(t))^2, R(t) = c t / 2 at the bin's centre, so that the waveform
    rendered at ``range_m`` gives every contribution the 1/R^2 of its own range (Eq. 7)."""
    r = (res.times_ns() + 0.5 * res.bin_ns) * RANGE_PER_NS
    return res.sigma * (np.asarray(range_m, np.float64)[:, None] / r) ** 2


def run_tile(k: int, plan_: Plan, scenes: TileScenes, survey: Survey, mcrt: MCRTSetup, setup: SensorSetup,
             out: Path, threads: int | None = None, progress=None) -> TileResult:
    """Trace and render tile ``k`` of the plan; write ``out`` (pulse table) and, with truth, its sibling."""
    cpu = time.process_time()
    rows = np.flatnonzero(plan_.tile == plan_.tiles[k])
    p = plan_.pulses.take(rows)
    prepared = scenes.build(plan_.tile_xy[k], len(rows), mcrt.n_rays, plan_.tile_m)
    rng = named_generator("survey", survey.seed, int(k))
    tables, truths, rays, saturated, sigma, late = [], [], 0, 0, 0.0, 0.0
    s = (plan_.ground_z - p.origin[:, 2]) / p.direction[:, 2]
    if prepared is not None:
        win = window_ns(prepared, p.origin, p.direction, mcrt.max_order)
        for a in range(0, len(rows), survey.chunk_pulses):
            sl = slice(a, a + survey.chunk_pulses)
            beams = Beams.from_divergence(p.origin[sl], p.direction[sl], survey.scanner.divergence_mrad, s[sl])
            res = trace(prepared, beams, seed=rng, threads=threads, window_ns=win, by_order=survey.truth,
                        **mcrt.kwargs(), **mcrt.budget(setup.system, setup.noise_sd, s[sl]))
            rays += int(res.rays.sum())
            sigma, late = sigma + float(res.total.sum()), late + float(res.sigma_dropped.sum())
            sim = render_sigma(at_range(res, s[sl]), res.t0_ns, s[sl], setup, rng, sigma_total=res.total)
            saturated += int(np.count_nonzero((sim.samples >= setup.digitizer_max).any(axis=1)))  # NaN pads: False
            tables.append(pulse_table(p.take(np.arange(len(rows))[sl]), rows[sl], sim, s[sl], survey.scanner.agc))
            if survey.truth:
                truths.append(truth_table(rows[sl], p.gps_time[sl], res))
            if progress is not None:
                progress.update(len(beams))
    elif progress is not None:
        progress.update(len(rows))
    table = pa.concat_tables(tables) if tables else pulse_table(p.take(slice(0, 0)), rows[:0], _empty_sim(), s[:0])
    with atomic_path(out) as tmp:
        pq.write_table(table, tmp)
    if survey.truth:
        tpath = out.with_suffix(".truth.parquet")
        with atomic_path(tpath) as tmp:
            empty = pa.table({"pulse_id": pa.array([], pa.int64())})
            pq.write_table(pa.concat_tables(truths) if truths else empty, tmp)
    echoes = table.column("n_echoes").to_numpy().astype(np.int64)
    return TileResult(len(rows), int(echoes.sum()), int(np.count_nonzero(echoes)), rays, time.process_time() - cpu,
                      saturated, sigma, late)


def _empty_sim() -> SimPulses:
    z = np.zeros(0)
    return SimPulses(np.zeros((0, 1), np.float32), np.zeros(0, np.int64), 1.0, z, np.zeros((0, 4)),
                     np.zeros((0, 4)), np.zeros(0, np.int16), z, np.zeros((0, 5), np.int64))


@functools.cache
def code_digest() -> bytes:
    """SHA-256 of the installed package's Python sources: a tile cached by other code is not reused."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parents[1]
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(path.read_bytes())
    return h.digest()


def run_key(scene: SurveyScene, survey: Survey, mcrt: MCRTSetup, setup_text: str) -> str:
    """A hash of everything the tile files depend on: the code, the scene's triangles and plant
    copies, the survey (its trajectory and S(t) files' bytes) and the settings."""
    h = hashlib.sha256(code_digest())
    if scene.static is not None:
        for a in (scene.static.triangles, scene.static.rho, scene.static.tau, scene.static.kind):
            h.update(np.ascontiguousarray(a).tobytes())
    if scene.plants is not None:
        h.update(repr(scene.plants.labels).encode())
        for a in (scene.plants.which, scene.plants.rotation, scene.plants.translation):
            h.update(np.ascontiguousarray(a).tobytes())
    for path in (survey.trajectory, survey.scanner.system_waveform):
        if path is not None:
            h.update(Path(path).read_bytes())
    h.update(repr((replace(survey, source=Path(survey.source).name), mcrt, setup_text)).encode())
    return h.hexdigest()[:16]


def summary(plan_: Plan, results: list[TileResult], wall_s: float, peak_mb: float, mcrt: MCRTSetup) -> dict:
    """The run summary written as summary.json."""
    cpu = sum(r.cpu_s for r in results)
    n = sum(r.pulses for r in results)
    return {"pulses_flown": plan_.n_flown, "pulses_traced": n, "pulses_recorded": sum(r.recorded for r in results),
            "returns": sum(r.returns for r in results),
            "saturated_pulses": sum(r.saturated for r in results),
            "tiles": len(plan_.tiles), "rays_per_pulse": mcrt.n_rays if mcrt.tolerance is None else None,
            "tolerance": mcrt.tolerance, "max_order": mcrt.max_order,
            "rays": sum(r.rays for r in results),
            "sigma_after_window": sum(r.sigma_late for r in results) / max(sum(r.sigma for r in results), 1e-300),
            "cpu_s": cpu, "wall_s": wall_s,
            "cpu_ms_per_pulse": 1000 * cpu / max(n, 1), "peak_memory_mb": peak_mb}


def write_summary(obj: dict, path: Path) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2) + "\n")
