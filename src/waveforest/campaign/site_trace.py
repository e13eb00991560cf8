"""Trace the campaign's sites: one true scene per site, all its pulses in one MCRT call.

Every site (field sample or target) is one unit of work: its true scene is built once
(:mod:`.scenes`), prepared once (Embree BVH) and every pulse of every dataset over it is
traced in a single batched :func:`waveforest.mcrt.trace` call. The rays of a field sample's
pulse: the adaptive budget (``campaign.tolerance``; :func:`site_budget`) against the true
sensor of its dataset, ``campaign.n_rays`` the fewest; planar targets at most
:data:`~.scenes.TARGET_RAYS` (exact whatever the count). Per dataset, the sigma(t) of
its pulses is trimmed to the bins that hold light (float32) and the noise-free unit-gain
analog peak of each pulse (what the AGC loop scales) is computed.

Parallelism: the sites are shared over worker threads (:func:`waveforest.workers.unordered_map`).
The result does not depend on the number of workers or on the order in which the sites
finish: a site's scene seed and MCRT key derive only from the master seed and the site id
(:mod:`.rng`), and the MCRT result does not depend on threads (:mod:`waveforest.mcrt.tracer`).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from waveforest.campaign.scenes import TARGET_RAYS, sample_scene, target_scene
from waveforest.campaign.truth_sensor import TruthSensor, unit_gain_peaks
from waveforest.constants import BIN_NS
from waveforest.mcrt import Beams, prepare, trace
from waveforest.rng import stream_seed31
from waveforest.workers import unordered_map

SIGMA_TRIM_REL = 1e-6
"""sigma(t) bins at the ends of a site's batch below this fraction of its largest bin are not kept."""


@dataclass(frozen=True)
class TraceSettings:
    """What every site's tracing shares (the campaign config and its true effects)."""

    seed: int
    n_rays: int
    max_order: int
    viewed_diameter_m: float
    specular: float
    hotspot: float
    trigger_loss: float
    ground_rho: float
    lai_jitter: float
    vegetation_effects: tuple[tuple[str, float], ...]
    sensors: tuple[TruthSensor, ...]
    """True sensor of each dataset, by dataset index."""
    bvh_quality: str
    """Embree BVH build quality of the site scenes (config ``campaign.bvh_quality``)."""
    sampler: str
    roulette: float
    """MCRT estimator (config ``mcrt.sampler``, ``mcrt.roulette``: the model's)."""
    tolerance: float | None = None
    """Adaptive budget of the field samples' pulses (config ``campaign.tolerance``): the recorded
    waveform's Monte Carlo SD as a fraction of the digitiser noise SD; None = ``n_rays`` rays."""
    max_rays: int = 0
    """Most rays per pulse of the adaptive budget (config ``mcrt.max_rays``)."""


@dataclass(frozen=True)
class SiteJob:
    """One site and its pulses (all datasets), in scene-local coordinates.

    Attributes
    ----------
    site, kind : str
        Site id; ``sample`` or ``target``.
    species : str
    height_m, rho, side_m, on_ground_rho, reach_m : float
        Sample species and field height; target reflectance, side, surrounding ground
        reflectance (NaN = none) and the largest reach of a pulse's viewed circle, m.
    origin : (n, 3) float64, m
        Sensor positions minus the site origin (x, y, ground z).
    direction : (n, 3) float64
        Unit sensor -> target directions.
    divergence_mrad, range_m : (n,) float64
        Beam divergence and range to the ground point, m.
    dataset : (n,) int64
        Dataset index of each pulse.
    rows : (n,) int64
        Row of each pulse in its dataset's pulse table.
    """

    site: str
    kind: str
    species: str
    height_m: float
    rho: float
    side_m: float
    on_ground_rho: float
    reach_m: float
    origin: np.ndarray
    direction: np.ndarray
    divergence_mrad: np.ndarray
    range_m: np.ndarray
    dataset: np.ndarray
    rows: np.ndarray

    def __len__(self) -> int:
        return len(self.rows)


@dataclass(frozen=True)
class SitePart:
    """The traced pulses of one dataset over one site."""

    site: str
    rows: np.ndarray        # (m,) int64 rows in the dataset's pulse table
    sigma: np.ndarray       # (m, n_bins) float32, per-bin sigma sums (trimmed)
    t0_ns: np.ndarray       # (m,) two-way time of bin 0's left edge, ns
    range_m: np.ndarray     # (m,) R of Eq. 7, m
    a0_dn: np.ndarray       # (m,) unit-gain noise-free analog peak, DN


@dataclass(frozen=True)
class SiteResult:
    """A traced site: its parts by dataset index, the true cover (samples) and timings."""

    site: str
    parts: dict
    cover: float | None
    scene_s: float
    trace_s: float


def trim(sigma: np.ndarray) -> tuple[int, np.ndarray]:
    """Drop the leading and trailing bins of a batch below :data:`SIGMA_TRIM_REL` of its peak.

    Parameters
    ----------
    sigma : (m, n_bins) float

    Returns
    -------
    first : int
        Index of the first kept bin.
    kept : (m, k) float32
    """
    peak = sigma.max() if sigma.size else 0.0
    if peak <= 0:
        return 0, np.zeros((sigma.shape[0], 1), dtype=np.float32)
    cols = np.flatnonzero(sigma.max(axis=0) > SIGMA_TRIM_REL * peak)
    a, b = int(cols[0]), int(cols[-1]) + 1
    return a, sigma[:, a:b].astype(np.float32)


AGC_HIGH_SD = 1.0
"""The adaptive budget assumes the AGC gain of the terrain level this many SDs above its mean
(``agc_bg_mean + agc_bg_sd``): a pulse recorded at a higher gain shows its error larger."""


def site_budget(job: SiteJob, st: TraceSettings) -> dict:
    """``trace`` keywords of the adaptive budget of a field sample's pulses (``{}``: fixed ``n_rays``).

    The recorded waveform of a pulse of dataset d is g S_d (x) sigma / R^2 plus noise of SD s_d
    (Eq. 7, the true sensor). The kernel is the unit-peak S(t) of the site's dataset of the
    narrowest pulse (the least smoothing: the error it shows is the largest); the noise of a
    pulse in the kernel's units is s_d R^2 / (g_d peak(S_d)), g_d the gain law at the terrain
    level :data:`AGC_HIGH_SD` SDs above its mean.
    """
    if st.tolerance is None:
        return {}
    present = [int(d) for d in np.unique(job.dataset)]
    narrow = st.sensors[min(present, key=lambda d: st.sensors[d].system_waveform().fwhm_ns)]
    kernel = narrow.system.s / narrow.system.s.max()
    scale = np.zeros(len(st.sensors))
    for d in present:
        t = st.sensors[d]
        g = float(t.agc.gain(t.agc.bg_mean + AGC_HIGH_SD * t.agc.bg_sd))
        scale[d] = t.noise_sd_dn / (max(g, 1e-6) * t.system.s.max())
    noise = scale[job.dataset] * job.range_m**2
    return dict(tolerance=st.tolerance, min_rays=st.n_rays, max_rays=max(st.max_rays, st.n_rays), kernel=kernel,
                noise=noise)


def trace_site(job: SiteJob, st: TraceSettings, threads: int | None = None) -> SiteResult:
    """Build the site's true scene, trace all its pulses, trim sigma and compute a0 per dataset."""

    t_start = time.perf_counter()
    if job.kind == "sample":
        scene = sample_scene(job.species, job.height_m, st.seed, job.site, ground_rho=st.ground_rho,
                             lai_jitter=st.lai_jitter, vegetation_effects=dict(st.vegetation_effects))
        n_rays = st.n_rays
        budget = site_budget(job, st)
    else:
        scene = target_scene(job.rho, job.side_m, job.on_ground_rho, job.reach_m)
        n_rays = min(TARGET_RAYS, st.n_rays)
        budget = {}
    prepared = prepare(scene, quality=st.bvh_quality)
    t_trace = time.perf_counter()
    beams = Beams.from_divergence(job.origin, job.direction, job.divergence_mrad, job.range_m)
    res = trace(prepared, beams, n_rays=n_rays, max_order=st.max_order, bin_ns=BIN_NS,
                viewed_diameter_m=st.viewed_diameter_m, seed=stream_seed31(st.seed, "trace", job.site),
                specular=st.specular, hotspot=st.hotspot, threads=threads, sampler=st.sampler,
                roulette=st.roulette, **budget)
    cover = None
    if job.kind == "sample":
        fh = res.first_hit_counts.astype(np.float64)
        cover = float(np.mean(fh[:, 1:4].sum(axis=1) / fh.sum(axis=1)))
    parts = {}
    for ds in np.unique(job.dataset):
        sel = np.flatnonzero(job.dataset == ds)
        b0, sig = trim(res.sigma[sel])
        t0 = res.t0_ns[sel] + b0 * BIN_NS
        rg = job.range_m[sel]
        a0 = unit_gain_peaks(st.sensors[int(ds)], sig, t0, rg, trigger_loss=st.trigger_loss)
        parts[int(ds)] = SitePart(job.site, job.rows[sel], sig, t0, rg, a0)
    return SiteResult(job.site, parts, cover, t_trace - t_start, time.perf_counter() - t_trace)


def trace_sites(jobs: list[SiteJob], settings: TraceSettings, workers: int = 1, *,
                progress: bool = True) -> dict[str, SiteResult]:
    """Trace every site (module docstring).

    Parameters
    ----------
    jobs : list of SiteJob
    settings : TraceSettings
    workers : int
        Threads to share the sites over (each traces serially); 1 = one site at a time, MCRT
        using Numba's threads.
    progress : bool
        Progress bar over sites (stderr).

    Returns
    -------
    dict
        Site id -> :class:`SiteResult`.
    """
    if workers < 1:
        raise ValueError(f"workers: expected >= 1, got {workers}")
    bar = tqdm(total=len(jobs), desc="synthesize: sites", unit="site", file=sys.stderr, disable=not progress)
    # the largest sites first: the workers finish together
    order = sorted(jobs, key=len, reverse=True)
    out: dict[str, SiteResult] = {}
    try:
        for _, r in unordered_map(lambda job: trace_site(job, settings), order, workers):
            out[r.site] = r
            bar.update()
        return out
    finally:
        bar.close()
