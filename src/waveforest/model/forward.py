"""One code path from a vegetation instance and beams to waveforms, echoes and features.

Used by ``simulate`` (real pulse geometry), ``sensitivity`` and ``sensor_study``:

    scene --mcrt.trace--> sigma(t) --sensor.render (Eq. 7)--> waveform
          --sensor.detect_echoes (CFD)--> echoes --sensor.first_echo_features--> features

The order of docs/method.md §(c): sigma and S(t) on the 0.05-ns grid, convolution, / R^2, noise,
sampling, rounding; then the CFD and the features exactly as for real waveforms.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit

from waveforest.constants import RANGE_PER_NS
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.mcrt import trace
from waveforest.sensor import CFDParams, FeatureParams, detect_echoes, first_echo_features, render
from waveforest.sensor.agc import divide_gain
from waveforest.sensor.signal import analog_waveforms

MAX_ECHOES = 4
"""DR echoes per pulse (ALS60, docs/method.md §(a))."""

GEOREF_TAU_S = 10.0
"""Correlation time of the modelled georeferencing drift (effect ``xy_error``), s: a GNSS/INS
error wanders over seconds, so the pulses of one pass over a field sample (well under a second
apart) share nearly one offset, and passes of different strips (tens of seconds and more apart)
nearly independent ones (:func:`georeferencing_drift`)."""


def split_effects(effects: dict | None) -> tuple[dict, dict, dict, float]:
    """Effects by the module that applies them (src/waveforest/effects.py).

    Returns
    -------
    vegetation : dict
        ``build_scene`` keyword arguments (understory, clumping, lad_shift, leaf_albedo).
    mcrt : dict
        ``trace`` keyword arguments (specular, hotspot).
    sensor : dict
        ``render`` keyword arguments (noise_autocorr, nonlinearity, trigger_loss).
    xy_error : float
        SD of the horizontal georeferencing drift of the beams, m (per axis; :func:`georeferencing_drift`).
    """
    veg, mcrt, sensor, xy = {}, {}, {}, 0.0
    for name, value in (effects or {}).items():
        if name not in CATALOGUE:
            raise WaveforestError(f"effect {name!r}: unknown; expected one of {', '.join(CATALOGUE)}")
        stage = CATALOGUE[name].stage
        if stage == "vegetation":
            veg[name] = float(value)
        elif stage == "mcrt":
            mcrt[name] = float(value)
        elif stage == "sensor":
            sensor[name] = float(value)
        elif name == "xy_error":
            xy = float(value)
        else:  # pragma: no cover - the catalogue has no other stage
            raise WaveforestError(f"effect {name!r}: stage {stage!r} is not handled")
    return veg, mcrt, sensor, xy


@njit(cache=True, nogil=True)
def _gauss_markov(z, t, tau_s):
    """(n, 2) unit Gauss-Markov values at times ``t`` from the (n, 2) normals ``z`` (a pulse with
    a non-finite time starts afresh)."""
    order = np.argsort(t)
    out = np.empty_like(z)
    prev = -1
    for k in range(z.shape[0]):
        i = order[k]
        dt = t[i] - t[prev] if prev >= 0 else np.inf
        phi = np.exp(-dt / tau_s) if np.isfinite(dt) else 0.0
        for a in range(z.shape[1]):
            out[i, a] = phi * out[prev, a] + np.sqrt(1.0 - phi * phi) * z[i, a] if phi > 0.0 else z[i, a]
        prev = i
    return out


def georeferencing_drift(z: np.ndarray, gps_time: np.ndarray, tau_s: float = GEOREF_TAU_S) -> np.ndarray:
    """A stationary Gauss-Markov drift of unit SD per axis at the pulses' GPS times.

    Parameters
    ----------
    z : (n, 2) float64
        Independent standard normal draws, one per pulse and axis.
    gps_time : (n,) float64, s
    tau_s : float, s
        Correlation time: corr(x_i, x_j) = exp(-|t_i - t_j| / tau_s).

    Returns
    -------
    (n, 2) float64: x_0 = z_0 and x_i = phi x_(i-1) + sqrt(1 - phi^2) z_i in time order, phi =
    exp(-dt / tau_s); the offsets of ``xy_error`` are xy_error times these (linear in it, so one
    seed gives common random numbers over its values).
    """
    return _gauss_markov(np.require(z, np.float64, ["C", "W"]), np.require(gps_time, np.float64, ["C", "W"]),
                         float(tau_s))


@njit(cache=True, nogil=True)
def _squared_correlation_sum(t, tau_s):
    """sum over i, j of exp(-2 |t_i - t_j| / tau_s) for the (n,) ascending times ``t``, in O(n)."""
    total = 0.0
    tail = 0.0  # sum over i < k of exp(-2 (t_k - t_i) / tau_s)
    for k in range(1, t.size):
        tail = np.exp(-2.0 * (t[k] - t[k - 1]) / tau_s) * (tail + 1.0)
        total += tail
    return t.size + 2.0 * total


def drift_dof(gps_time: np.ndarray, group: np.ndarray, tau_s: float = GEOREF_TAU_S) -> float:
    """Independent values per axis that the pulses hold of the drift of :func:`georeferencing_drift`.

    ν = n^2 / sum_ij corr(x_i, x_j)^2: the mean square of one axis' drift over the n pulses,
    divided by its variance, has the mean and variance of chi^2_ν / ν. Pulses of different
    groups (datasets: flights on different days) and pulses with a non-finite time count as
    independent.

    Parameters
    ----------
    gps_time : (n,) float64, s
    group : (n,) array
    tau_s : float, s
    """
    t = np.asarray(gps_time, dtype=np.float64)
    g = np.asarray(group)
    finite = np.isfinite(t)
    pairs = float((~finite).sum())
    for key in np.unique(g[finite]):
        pairs += _squared_correlation_sum(np.sort(t[finite & (g == key)]), float(tau_s))
    return float(t.size) ** 2 / pairs if pairs > 0 else 0.0


@dataclass(frozen=True)
class SensorSetup:
    """Everything between sigma(t) and features for one dataset (or study setting).

    Attributes
    ----------
    system : waveforest.sensor.SystemWaveform
        S(t), DN m^2 per unit sigma (Eq. 7).
    noise_mean, noise_sd : float, DN
    sampling_ns : float, ns
    cfd : waveforest.sensor.CFDParams (resolved against ``system.fwhm_ns``)
    features : waveforest.sensor.FeatureParams
    record_ns : float, ns
    pre_trigger_m : (float, float), m
    digitizer_max : int, DN
    render_effects : dict
        noise_autocorr, nonlinearity, trigger_loss (effects; off by default).
    range_correction : waveforest.sensor.RangeCorrection or None
        Amplitude-dependent range correction applied to the simulated CFD echoes.
    """

    system: object
    noise_mean: float
    noise_sd: float
    sampling_ns: float
    cfd: object
    features: object
    record_ns: float
    pre_trigger_m: tuple
    digitizer_max: int
    render_effects: dict = field(default_factory=dict)
    range_correction: object = None

    def with_system(self, system, cfd: CFDParams) -> SensorSetup:
        """The same setup with another S(t); ``cfd`` (unresolved) takes the delay and dead time of its FWHM."""

        return replace(self, system=system, cfd=cfd.resolved(system.fwhm_ns))


@dataclass(frozen=True)
class SensorSettings:
    """The sensor model of the config (section ``sensor``), before an S(t), noise and sampling are known.

    Attributes
    ----------
    record_ns : float, ns
    pre_trigger_m : (float, float), m
    digitizer_max : int, DN
    cfd : CFDParams
        Unresolved: delay and dead time None follow the S(t)'s FWHM.
    features : FeatureParams
    """

    record_ns: float
    pre_trigger_m: tuple
    digitizer_max: int
    cfd: CFDParams
    features: FeatureParams

    def setup(self, system, noise_mean: float, noise_sd: float, sampling_ns: float,
              render_effects: dict | None = None, range_correction=None, cfd: CFDParams | None = None) -> SensorSetup:
        """The :class:`SensorSetup` with S(t) ``system``, noise (DN) and sampling (ns).

        ``cfd``: the calibration's CFD (that of its range correction); None = :attr:`cfd`.
        """

        return SensorSetup(
            system=system, noise_mean=float(noise_mean), noise_sd=float(noise_sd),
            sampling_ns=float(sampling_ns), cfd=(cfd or self.cfd).resolved(system.fwhm_ns),
            features=self.features, record_ns=float(self.record_ns), pre_trigger_m=tuple(self.pre_trigger_m),
            digitizer_max=int(self.digitizer_max), render_effects=dict(render_effects or {}),
            range_correction=range_correction,
        )


@dataclass(frozen=True)
class MCRTSetup:
    """Keyword arguments of ``waveforest.mcrt.trace`` (config section ``mcrt`` plus mcrt effects).

    The ray budget: with ``tolerance`` None, ``n_rays`` rays per pulse; else, wherever the
    sensor is known (:meth:`budget`), an adaptive budget per pulse between ``min_rays`` and
    ``max_rays`` that stops once the Monte Carlo SD of the recorded waveform is ``tolerance``
    times the digitiser noise SD (docs/method.md §(d), "Ray budget"). Usage::

        res = trace(scene, beams, seed=s, **mcrt.kwargs(), **mcrt.budget(system, noise_sd, range_m, gain))
    """

    n_rays: int
    max_order: int
    bin_ns: float
    viewed_diameter_m: float
    sampler: str
    roulette: float
    tolerance: float | None
    min_rays: int
    max_rays: int
    effects: dict = field(default_factory=dict)

    def kwargs(self) -> dict:
        """The keyword arguments of ``trace`` with the fixed budget (``n_rays``; effects included)."""
        return dict(n_rays=self.n_rays, max_order=self.max_order, bin_ns=self.bin_ns,
                    viewed_diameter_m=self.viewed_diameter_m, sampler=self.sampler, roulette=self.roulette,
                    **self.effects)

    def budget(self, system, noise_sd: float, range_m, gain=None) -> dict:
        """The ``trace`` keywords of the adaptive budget for pulses recorded as
        V = g S (x) sigma / R^2 + noise of SD ``noise_sd`` (Eq. 7): ``{}`` when ``tolerance`` is None.

        Parameters
        ----------
        system : waveforest.sensor.SystemWaveform
            S(t) on the sigma grid, DN m^2 per unit sigma.
        noise_sd : float, DN
        range_m : float or (n,) float64, R of Eq. 7, m
        gain : (n,) float64, optional
            Signal gains g (the AGC gains of twinned real pulses); None = 1.
        """
        if self.tolerance is None:
            return {}
        g = 1.0 if gain is None else np.asarray(gain, dtype=np.float64)
        noise = float(noise_sd) * np.asarray(range_m, dtype=np.float64) ** 2 / g
        return dict(tolerance=self.tolerance, min_rays=self.min_rays, max_rays=self.max_rays,
                    kernel=np.asarray(system.s, dtype=np.float64), noise=noise)


@dataclass
class SimPulses:
    """Simulated pulses of one batch.

    Attributes
    ----------
    samples : (n, n_s) float32, DN (NaN beyond ``lengths``)
    lengths : (n,) int64
    sampling_ns : float
    first_sample_ns : (n,) float64, two-way time from emission of sample 0, ns (NaN: no trigger)
    echo_times_ns : (n, 4) float64, CFD echo times from the first sample, NaN-padded
    echo_amplitudes : (n, 4) float64, DN above the noise mean
    n_echoes : (n,) int16
    sigma_total : (n,) float64, total sigma of the pulse (all orders)
    first_hit_counts : (n, 5) int64 (rays first hitting ground, leaf, wood, other; misses)
    rays : (n,) int64 or None, MCRT rays each pulse used (``TraceResult.rays``)
    """

    samples: np.ndarray
    lengths: np.ndarray
    sampling_ns: float
    first_sample_ns: np.ndarray
    echo_times_ns: np.ndarray
    echo_amplitudes: np.ndarray
    n_echoes: np.ndarray
    sigma_total: np.ndarray
    first_hit_counts: np.ndarray
    rays: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.lengths)

    def echo_ranges_m(self) -> np.ndarray:
        """(n, 4) one-way range from the sensor of each echo, m (NaN-padded)."""
        return (self.first_sample_ns[:, None] + self.echo_times_ns) * RANGE_PER_NS

    def features(self, setup: SensorSetup) -> dict:
        """First-echo features (docs/method.md §(h)) of every pulse: Npeaks, Apeak, FWHM, E (NaN without echo)."""

        return first_echo_features(self.samples, self.lengths, self.sampling_ns, self.echo_times_ns[:, 0],
                                   setup.noise_mean, setup.noise_sd,
                                   segment_sd=setup.features.segment_sd,
                                   peak_rise_sd=setup.features.peak_rise_sd,
                                   echo_search_ns=setup.features.echo_search_ns)


def twin_echoes(samples, lengths, sampling_ns, setup: SensorSetup, gain=None):
    """CFD echoes of AGC-normalised waveforms, found as a simulated twin's are.

    The setup's CFD and range correction, armed on the recorded noise: noise_sd / g in
    normalised DN (``gain`` None: g = 1). Returns :class:`waveforest.sensor.Echoes`.
    """

    noise_sd = setup.noise_sd if gain is None else setup.noise_sd / np.asarray(gain, dtype=np.float64)
    return detect_echoes(samples, lengths, sampling_ns, setup.noise_mean, noise_sd, setup.cfd,
                         max_echoes=MAX_ECHOES, range_correction=setup.range_correction)


def render_sigma(sigma: np.ndarray, t0_ns: np.ndarray, range_m: np.ndarray, setup: SensorSetup,
                 rng: np.random.Generator, sigma_total: np.ndarray | None = None,
                 first_hit_counts: np.ndarray | None = None, gain: np.ndarray | None = None) -> SimPulses:
    """sigma(t) -> waveforms (Eq. 7) -> CFD echoes, for a batch of pulses.

    Parameters
    ----------
    sigma : (n, n_bins) float64, per-bin sums on the 0.05-ns grid (mcrt.TraceResult.sigma)
    t0_ns : (n,) float64, two-way time from emission of bin 0's left edge, ns
    range_m : (n,) float64, R of Eq. 7, m
    setup : SensorSetup
    rng : numpy Generator (sampling phase, pre-trigger, noise)
    gain : (n,) float64, optional
        AGC gains (Eq. 1) of the real pulses these are twins of. Each waveform is then
        recorded as the sensor records it, signal x g + noise (trigger, saturation, rounding
        and clipping on the gained signal), and AGC-normalised as the real one is,
        (V - c-bar)/g + c-bar: its noise has SD noise_sd / g and its rounding steps 1/g DN,
        like the real normalised waveform's (the AGC does not gain the noise, docs/method.md §(b)).
        The CFD arms at ``cfd.arming_sd`` SDs of the recorded noise, as the DR circuits see
        it: noise_sd / g in normalised DN. None: gain 1 (a pulse of no real recording).
    """

    n = sigma.shape[0]
    r = render(sigma, t0_ns, range_m, setup.system, setup.noise_mean, setup.noise_sd, setup.sampling_ns, rng,
               record_ns=setup.record_ns, pre_trigger_m=tuple(setup.pre_trigger_m),
               digitizer_max=setup.digitizer_max, cfd=setup.cfd, gain=gain, **setup.render_effects)
    samples = np.asarray(r.samples, dtype=np.float32)
    if gain is not None:
        samples = divide_gain(samples, gain, setup.noise_mean)
    lengths = np.full(n, samples.shape[1], dtype=np.int64)
    first = np.asarray(r.first_sample_ns, dtype=np.float64)
    times, amps, counts = twin_echoes(samples, lengths, setup.sampling_ns, setup, gain)
    no_trigger = ~np.isfinite(np.asarray(r.trigger_ns, dtype=float))
    counts = np.where(no_trigger, 0, counts).astype(np.int16)
    times = np.where(no_trigger[:, None], np.nan, times)
    amps = np.where(no_trigger[:, None], np.nan, amps)
    return SimPulses(
        samples=samples, lengths=lengths, sampling_ns=float(setup.sampling_ns), first_sample_ns=first,
        echo_times_ns=times, echo_amplitudes=amps, n_echoes=counts,
        sigma_total=np.zeros(n) if sigma_total is None else sigma_total,
        first_hit_counts=np.zeros((n, 5), np.int64) if first_hit_counts is None else first_hit_counts,
    )


FEATURE_SAMPLING_NS = 1.0
"""Sampling of :func:`noise_free_waveform`'s features (the ALS60's 1 ns)."""

SEGMENT_SD = 3.0
"""The first echo's segment of :func:`noise_free_waveform`: above this many noise SDs (§(h))."""


def noise_free_waveforms(sigma, t0_ns, bin_ns: float, system, noise_sd, range_m):
    """The noise-free waveforms recorded of sigma(t) ``sigma`` (n, n_bins) starting at ``t0_ns``
    (n,) in bins of ``bin_ns`` (a TraceResult's), Eq. 7 with S(t) ``system`` at R = ``range_m``
    (float or (n,)), DN above the noise mean, and their first echoes' features: the quantities
    whose Monte Carlo spread the ray budget bounds (§(d)).

    Returns (t_first_ns (n,) two-way time of the first sigma-grid sample, v (n, k) DN on the
    sigma grid, w (n, m) DN every :data:`FEATURE_SAMPLING_NS` from v's first sample, features
    {"Apeak": DN, "E": DN ns, "FWHM": ns} of (n,)): the first echo is the first local maximum
    of w above :data:`SEGMENT_SD` ``noise_sd`` (float or (n,); NaN without one), its segment
    the run above that level.
    """
    v, t_first = analog_waveforms(sigma, t0_ns, range_m, system, bin_ns=bin_ns)
    w = v[:, ::int(round(FEATURE_SAMPLING_NS / bin_ns))]
    n, m = w.shape
    sd = np.broadcast_to(np.asarray(noise_sd, np.float64), (n,))
    above = w >= SEGMENT_SD * sd[:, None]
    start = np.argmax(above, axis=1)
    falls = (np.diff(w, axis=1) < 0) & (np.arange(m - 1)[None, :] >= start[:, None])
    peak = np.where(falls.any(axis=1), np.argmax(falls, axis=1), m - 1)
    peak_ns = np.where(above.any(axis=1), peak * FEATURE_SAMPLING_NS, np.nan)
    f = first_echo_features(w, None, FEATURE_SAMPLING_NS, peak_ns, 0.0, sd, SEGMENT_SD)
    return t_first, v, w, {k: f[k] for k in ("Apeak", "E", "FWHM")}


def noise_free_waveform(result, system, noise_sd: float, range_m: float, i: int = 0):
    """Pulse ``i`` of a TraceResult through :func:`noise_free_waveforms`: (t_ns (k,) two-way time
    from emission of each sigma-grid sample, v (k,) DN, {"Apeak": DN, "E": DN ns, "FWHM": ns})."""
    t_first, v, _, f = noise_free_waveforms(result.sigma[i:i + 1], result.t0_ns[i:i + 1], result.bin_ns, system,
                                            noise_sd, range_m)
    return t_first[0] + result.bin_ns * np.arange(v.shape[1]), v[0], {k: float(x[0]) for k, x in f.items()}


def trace_and_render(scene, beams, range_m: np.ndarray, mcrt: MCRTSetup, setup: SensorSetup,
                     trace_seed: int, rng: np.random.Generator, threads: int | None = None,
                     gain: np.ndarray | None = None, tracer=trace):
    """MCRT of ``beams`` through ``scene`` (a Scene or PreparedScene), then :func:`render_sigma`
    (``gain``: the AGC gains of the real pulses twinned, see there). The ray budget is
    ``mcrt``'s: adaptive to ``setup``'s S(t) and noise at each pulse's R and gain (:meth:`MCRTSetup.budget`)
    unless its tolerance is None. ``tracer``: :func:`waveforest.mcrt.trace` or a stand-in with its
    signature and results (a cache of them).

    Returns
    -------
    (SimPulses, TraceResult)
    """

    res = tracer(scene, beams, seed=int(trace_seed), threads=threads, **mcrt.kwargs(),
                 **mcrt.budget(setup.system, setup.noise_sd, range_m, gain))
    sim = render_sigma(res.sigma, res.t0_ns, np.asarray(range_m, dtype=float), setup, rng,
                       sigma_total=res.total, first_hit_counts=res.first_hit_counts, gain=gain)
    sim.rays = res.rays
    return sim, res
