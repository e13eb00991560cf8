"""A LAS waveform file -> an echo point cloud by Gaussian decomposition, streamed
(:mod:`waveforest.sensor.decompose`; docs/method.md §(f2)).

Each batch of pulses from :class:`waveforest.io.las.read.WaveformPulseReader` is decomposed
and its echoes written to a LAS 1.4 point format 6 file with extra bytes
(:mod:`waveforest.io.las.extra_bytes`); memory is one batch. Every waveform packet of a pulse
is decomposed (a RIEGL pulse may hold its returns in several), and a pulse's echoes are numbered
together. Point format 9 keeps the
waveforms: each echo points into its packet, in a copy of the source's waveform data
(a ``.wdp`` beside the output), at its time within the packet. Per echo: the centre along the
beam (``anchor + dir * t * c/2``), range, amplitude, SD, FWHM, energy, its packet's fit residual,
echo number and count, the pulse's flags (:data:`waveforest.sensor.decompose.FLAGS`) and the
backscatter cross-section (Eq. F2):

    sigma_bs = C_cal * R^4 * A * s                                                   (F2)

(Wagner et al. 2006, with a Gaussian system pulse of fixed width). Without a calibration
constant ``C_cal`` the relative value ``(R / 1000 m)^4 * A * s`` (DN ns) is written;
:func:`calibration_constant` gives ``C_cal`` from a reference target of known reflectance.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from waveforest.atomic import atomic_path, output_files, write_json
from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError
from waveforest.io.las.extra_bytes import EchoCloudWriter, copy_waveform_data, echo_header
from waveforest.io.las.file import open_point_reader
from waveforest.io.las.format import WAVEFORM_HEADER_SIZE
from waveforest.io.las.info import projection_records
from waveforest.io.las.pulses import refuse_overwriting_input, sensor_locator
from waveforest.io.las.read import WaveformPulseReader
from waveforest.io.pulses import list_to_padded
from waveforest.model.self_tuning import Pulses
from waveforest.sensor.calibration import load_calibration
from waveforest.sensor.decompose import FLAG_NOISE, FLAGS, decompose
from waveforest.sensor.self_calibration import tail_noise

REFERENCE_RANGE_M = 1000.0
"""Range the relative cross-section is scaled to, m."""


@dataclass(frozen=True)
class DecomposeSettings:
    """How waveforms are decomposed (:func:`waveforest.sensor.decompose.decompose`).

    min_snr : detection level, noise SDs.  max_echoes : most echoes per pulse.
    fixed_width : every echo has the system pulse's width (needs a CFD/calibration JSON).
    calibration_constant : C_cal of Eq. F2, m^2 / (m^4 DN ns); None: relative cross-sections.
    batch_pulses : pulses decomposed at once (memory).
    point_format : 6, or 9 to keep the waveform packets (a ``.wdp`` beside the output).
    """

    min_snr: float = 3.0
    max_echoes: int = 8
    fixed_width: bool = False
    calibration_constant: float | None = None
    batch_pulses: int = 20000
    point_format: int = 6


@dataclass
class DecomposeSummary:
    """What :func:`decompose_file` wrote and found. ``n_pulses_several_packets``: pulses whose
    returns lie in more than one waveform packet (each packet is decomposed; the pulse's echoes
    are numbered together); ``n_packets``: the waveforms decomposed."""

    out: Path
    n_pulses: int = 0
    n_echoes: int = 0
    echoes_per_pulse: dict = field(default_factory=dict)
    flags: dict = field(default_factory=dict)
    noise_mean: float = math.nan
    noise_sd: float = math.nan
    pulse_fwhm_ns: float | None = None
    noise_source: str = ""
    n_packets: int = 0
    n_pulses_several_packets: int = 0
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return {"out": str(self.out), "n_pulses": self.n_pulses, "n_echoes": self.n_echoes,
                "echoes_per_pulse": {str(k): v for k, v in sorted(self.echoes_per_pulse.items())},
                "flagged_pulses": self.flags, "noise_mean_dn": self.noise_mean, "noise_sd_dn": self.noise_sd,
                "pulse_fwhm_ns": self.pulse_fwhm_ns, "noise_source": self.noise_source,
                "n_packets": self.n_packets, "n_pulses_several_packets": self.n_pulses_several_packets, "seconds": round(self.seconds, 3)}


def calibration_constant(reflectance: float, incidence_deg: float, divergence_mrad: float, range_m: float,
                         amplitude_dn: float, sigma_ns: float) -> float:
    """C_cal of Eq. F2 from an extended Lambertian reference target of known ``reflectance``,
    whose cross-section is ``pi rho R^2 beta^2 cos(alpha)`` (beta: full divergence, rad)."""
    beta = divergence_mrad * 1e-3
    sigma_ref = math.pi * reflectance * range_m ** 2 * beta ** 2 * math.cos(math.radians(incidence_deg))
    return sigma_ref / (range_m ** 4 * amplitude_dn * sigma_ns)


def noise_and_width(cfd_path, first: pa.Table) -> tuple[float, float, float | None, str]:
    """Noise mean and SD (DN), system pulse FWHM (ns, None: unknown) and where they came from:
    the CFD or calibration JSON, else the tail noise of the first batch (no FWHM)."""
    if cfd_path is not None:
        cal = load_calibration(cfd_path)
        fwhm = cal.meta.get("fwhm_ns") or cal.meta.get("system_fwhm_ns")
        return cal.noise_mean, cal.noise_sd, (float(fwhm) if fwhm else None), str(cfd_path)
    p = Pulses.of(first)
    try:
        noise = tail_noise(p.samples, p.lengths, p.sampling_ns, p.last_echo_ns)
    except ValueError as exc:
        raise WaveforestError(f"cannot estimate the noise from the waveforms' tails ({exc}); give --cfd "
                              "(the JSON of `waveforest tune-cfd`)") from None
    return noise.mean, noise.sd, None, "tail samples of the first batch"


def pulse_numbers(pulse_id: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows grouped in runs of equal ``pulse_id`` (a batch: one row per waveform packet, a pulse's
    packets consecutive) -> (each row's run, numbered from 0; each run's first row)."""
    first = np.ones(len(pulse_id), bool)
    first[1:] = pulse_id[1:] != pulse_id[:-1]
    return np.cumsum(first) - 1, np.flatnonzero(first)


def pulse_flags(flags: np.ndarray, firsts: np.ndarray) -> np.ndarray:
    """Flags (:data:`FLAGS`) of each pulse from those of its packets (rows ``firsts[j]`` up to
    the next pulse's): any packet's flag, but "all noise" only if every packet is all noise."""
    if not len(firsts):
        return flags[:0]
    noise = np.uint8(FLAG_NOISE)
    return (np.bitwise_or.reduceat(flags, firsts) & ~noise) | np.bitwise_and.reduceat(flags & noise, firsts)


def echo_columns(batch: pa.Table, dec, settings: DecomposeSettings, first_pulse: int) -> dict:
    """The echoes of one decomposed batch as flat point columns (:class:`EchoCloudWriter`);
    a pulse's echoes from all its packets are numbered together along the beam."""
    k = dec.n_echoes.astype(np.int64)
    rows = np.repeat(np.arange(len(k)), k)
    row_pulse, firsts = pulse_numbers(batch.column("pulse_id").to_numpy())
    pulse = row_pulse[rows]
    has = np.isfinite(dec.time_ns)  # found echoes are the first k of each row, in time order
    t = dec.time_ns[has]
    col = lambda c: batch.column(c).to_numpy(zero_copy_only=False).astype(np.float64)[rows]  # noqa: E731
    d = t * RANGE_PER_NS
    xyz = {a: col(f"anchor_{a}") + col(f"dir_{a}") * d for a in "xyz"}
    to_sensor = np.sqrt(sum((col(f"anchor_{a}") - col(f"sensor_{a}")) ** 2 for a in "xyz"))
    rng = to_sensor + d
    amp, sig = dec.amplitude[has], dec.sigma_ns[has]
    if settings.calibration_constant is None:
        cross = (rng / REFERENCE_RANGE_M) ** 4 * amp * sig
    else:
        cross = settings.calibration_constant * rng ** 4 * amp * sig
    along = sum(xyz[a] * col(f"dir_{a}") for a in "xyz")  # distance down the beam: the packets' common axis
    order = np.lexsort((along, pulse))
    group, starts = pulse_numbers(pulse[order])
    number, count = np.empty(len(order), np.int64), np.empty(len(order), np.int64)
    number[order] = np.arange(len(order)) - starts[group] + 1
    count[order] = np.diff(np.append(starts, len(order)))[group]
    out = {**xyz, "gps_time": col("gps_time"), "scan_angle_deg": col("scan_angle_deg"),
           "return_number": number, "number_of_returns": count, "intensity": amp,
           "pulse_id": first_pulse + pulse, "echo_time_ns": t, "range_m": rng, "amplitude_dn": amp,
           "sigma_ns": sig, "fwhm_ns": dec.fwhm_ns[has], "energy_dn_ns": dec.energy[has],
           "residual_dn": dec.rms_residual[rows], "flags": pulse_flags(dec.flags, firsts)[pulse], "cross_section": cross}
    if "wave_packet_index" in batch.column_names:  # point format 9: the echo's packet, t in ps, -dir * c/2 per ps
        out.update({c: batch.column(c).to_numpy()[rows] for c in
                    ("wave_packet_index", "wave_packet_offset", "wave_packet_bytes")})
        out["return_point_ps"] = t * 1000.0
        out.update({f"{a}_t": -col(f"dir_{a}") * (RANGE_PER_NS / 1000.0) for a in "xyz"})
    return out


def decompose_file(las_path, out_path, settings: DecomposeSettings, *, cfd_path=None, trajectory=None,
                   nominal_range_m: float | None = None, progress: bool = True) -> DecomposeSummary:
    """Decompose every waveform of ``las_path`` into ``out_path`` (.las or .laz) and a summary
    JSON beside it (``<out>.json``); with ``settings.point_format`` 9 also the waveform data
    (``out_path`` with suffix ``.wdp``); all written atomically, together.

    Raises
    ------
    WaveforestError
        An output name that is not .las/.laz or would overwrite the input LAS or its waveform
        file, unreadable input, a bad CFD JSON, or noise that cannot be estimated.
    """
    from tqdm import tqdm

    las_path, out_path = Path(las_path), Path(out_path)
    if out_path.suffix.lower() not in (".las", ".laz"):
        raise WaveforestError(f"{out_path}: expected a .las or .laz output file")
    if settings.point_format not in (6, 9):
        raise WaveforestError(f"point format {settings.point_format}: expected 6 or 9")
    refuse_overwriting_input(out_path, las_path)
    keep_waves = settings.point_format == 9
    wdp = out_path.with_suffix(".wdp")
    locate, _ = sensor_locator(trajectory, nominal_range_m)
    reader = WaveformPulseReader(las_path, locate=locate, agc_attribute=None, batch_pulses=settings.batch_pulses,
                                 tmp_dir=out_path.parent, packets=keep_waves, by_packet=True)
    las = reader.las
    if keep_waves and wdp.resolve() in (las.waveform.path.resolve(), las_path.with_suffix(".wdp").resolve()):
        raise WaveforestError(f"{out_path}: its waveforms would go to {wdp}, the input's own; choose another name")
    with open_point_reader(las) as pr:
        vlrs = [v for v in pr.header.vlrs if type(v).__name__ in ("WktCoordinateSystemVlr", "GeoKeyDirectoryVlr",
                                                                   "GeoDoubleParamsVlr", "GeoAsciiParamsVlr")]
    vlrs += projection_records(las.projection_evlrs)
    header = echo_header(las.scales, las.offsets, vlrs,
                         "relative" if settings.calibration_constant is None else "m2",
                         descriptors=las.descriptors if keep_waves else None)
    summary = DecomposeSummary(out_path)
    started = time.perf_counter()
    total = int(las.header_points_by_return[0]) or None  # an estimate: pulses may lack a first return
    batches = iter(reader)
    with output_files(), tqdm(total=total, unit="waveform", unit_scale=True, disable=not progress,
                              file=sys.stderr, desc=f"decompose {las_path.name}") as bar:
        with atomic_path(out_path) as tmp, EchoCloudWriter(tmp, header, out_path.suffix.lower() == ".laz") as w:
            try:
                for batch in batches:
                    if summary.n_pulses == 0:
                        mean, sd, fwhm, source = noise_and_width(cfd_path, batch)
                        summary.noise_mean, summary.noise_sd = mean, sd
                        summary.pulse_fwhm_ns, summary.noise_source = fwhm, source
                        if settings.fixed_width and fwhm is None:
                            raise WaveforestError("--fixed-width needs the system pulse FWHM: give --cfd")
                    x, lens = list_to_padded(batch.column("samples"))
                    dt = batch.column("sampling_ns").to_numpy(zero_copy_only=False).astype(np.float64)
                    dec = decompose(x, lens, dt, summary.noise_mean, summary.noise_sd,
                                    pulse_fwhm_ns=summary.pulse_fwhm_ns, fixed_width=settings.fixed_width,
                                    min_snr=settings.min_snr, max_echoes=settings.max_echoes)
                    w.write(echo_columns(batch, dec, settings, summary.n_pulses))
                    pulses = _count(summary, dec, batch.column("pulse_id").to_numpy())
                    if bar.total is not None and bar.n + pulses > bar.total:
                        bar.total = bar.n + pulses  # past the estimate: never a bare counter
                    bar.update(pulses)
            finally:
                batches.close()
            bar.total = bar.n  # the true count
            bar.refresh()
        if keep_waves:
            wf = las.waveform  # an internal record may be followed by EVLRs: its own length
            size = WAVEFORM_HEADER_SIZE + wf.record_length if wf.storage == "internal" and wf.header_ok else wf.size
            with atomic_path(wdp) as tmp:
                copy_waveform_data(wf.path, wf.base, size, tmp)
        summary.n_pulses_several_packets = reader.stats.n_split_pulses
        summary.seconds = time.perf_counter() - started
        write_json(summary.as_dict(), out_path.with_name(out_path.name + ".json"))
    return summary


def _count(summary: DecomposeSummary, dec, pulse_id: np.ndarray) -> int:
    """Add a batch's pulses (rows grouped by ``pulse_id``), echoes and flags to ``summary``; return its pulses."""
    _, firsts = pulse_numbers(pulse_id)
    n_echoes = np.add.reduceat(dec.n_echoes.astype(np.int64), firsts) if len(firsts) else np.zeros(0, np.int64)
    flags = pulse_flags(dec.flags, firsts)
    summary.n_pulses += len(firsts)
    summary.n_packets += len(pulse_id)
    summary.n_echoes += int(n_echoes.sum())
    for k, c in zip(*np.unique(n_echoes, return_counts=True)):
        summary.echoes_per_pulse[int(k)] = summary.echoes_per_pulse.get(int(k), 0) + int(c)
    for bit, name in FLAGS.items():
        c = int(np.count_nonzero(flags & bit))
        if c:
            summary.flags[name] = summary.flags.get(name, 0) + c
    return len(firsts)
