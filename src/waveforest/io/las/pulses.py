"""A LAS waveform file -> a pulse table in Parquet, streamed.

Streams :class:`waveforest.io.las.read.WaveformPulseReader` batches into
:func:`waveforest.io.pulses.write_pulse_batches` (atomic: a failure leaves no output and no temporary
file). Sensor positions come from a trajectory CSV, from a nominal range (the sensor that far
before the first echo along the beam), or are left unknown (NaN): :func:`sensor_locator`.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path

from waveforest.atomic import output_folder
from waveforest.errors import WaveforestError
from waveforest.io.las.file import find_wdp
from waveforest.io.las.read import (
    DEFAULT_BATCH_PULSES,
    DEFAULT_BUCKET_POINTS,
    DEFAULT_CHUNK_POINTS,
    LasWaveformFile,
    WaveformPulseReader,
    with_rate,
)
from waveforest.io.pulses import write_pulse_batches
from waveforest.io.trajectory import nominal_range_locator, read_trajectory, trajectory_locator


@dataclass(frozen=True)
class IngestResult:
    """What :func:`las_to_pulses` wrote.

    Attributes
    ----------
    out : Path
        The Parquet pulse table.
    n_pulses : int
        Pulse rows written.
    n_points : int
        LAS points read.
    n_without_waveform : int
        Pulses skipped because none of their returns has a waveform packet.
    n_bad_gps : int
        Points dropped for a non-finite GPS time.
    n_bad_geometry : int
        Points kept without their waveform packet (unusable beam geometry).
    n_split_pulses : int
        Pulses whose returns sit in more than one packet.
    agc_attribute : str or None
        The point dimension the AGC was read from (None: no AGC, column is NaN).
    sensor : str
        ``trajectory``, ``nominal`` or ``unknown``.
    las : LasWaveformFile
        The checked input file.
    """

    out: Path
    n_pulses: int
    n_points: int
    n_without_waveform: int
    n_split_pulses: int
    n_bad_gps: int
    n_bad_geometry: int
    agc_attribute: str | None
    sensor: str
    las: LasWaveformFile

    def summary(self) -> str:
        """One line for the CLI."""
        agc = f"AGC from {self.agc_attribute}" if self.agc_attribute else "no AGC"
        extra = "".join(
            f", {n:,} {what}"
            for n, what in (
                (self.n_bad_gps, "points with a non-finite GPS time dropped"),
                (self.n_bad_geometry, "points with an unusable beam geometry kept without their packet"),
                (self.n_without_waveform, "pulses without waveform skipped"),
            )
            if n
        )
        return (
            f"wrote {self.out}: {self.n_pulses:,} pulses from {self.n_points:,} points of {self.las.path.name} "
            f"(LAS {self.las.version}, format {self.las.point_format}, {self.las.waveform.storage} waveforms; "
            f"{agc}; sensor {self.sensor}{extra})"
        )


def sensor_locator(trajectory, nominal_range_m) -> tuple[object, str]:
    """The reader's ``locate`` callable and the ``sensor`` label: from a trajectory CSV
    (``"trajectory"``), a nominal range, m (``"nominal"``), or neither (None, ``"unknown"``).
    Both given raise :class:`WaveforestError`."""
    if trajectory is not None and nominal_range_m is not None:
        raise WaveforestError("give either a trajectory or a nominal range, not both")
    if trajectory is not None:
        return trajectory_locator(read_trajectory(trajectory)), "trajectory"
    if nominal_range_m is not None:
        return nominal_range_locator(float(nominal_range_m)), "nominal"
    return None, "unknown"


def refuse_overwriting_input(out: str | os.PathLike, las_path: str | os.PathLike) -> None:
    """A :class:`WaveforestError` when ``out`` is the LAS file ``las_path`` or the ``.wdp``
    beside it (the same file by path or by inode): writing it would destroy the input."""
    out, las_path = Path(out), Path(las_path)
    inputs = [p for p in (las_path, find_wdp(las_path)) if p is not None]
    for p in inputs:
        same = out.resolve() == p.resolve()
        if not same and out.exists() and p.exists():
            same = os.path.samefile(out, p)
        if same:
            raise WaveforestError(f"{out}: the output would overwrite the input {p.name}")


def las_to_pulses(
    las_path: str | os.PathLike,
    out: str | os.PathLike,
    *,
    dataset: str | None = None,
    trajectory: str | os.PathLike | None = None,
    nominal_range_m: float | None = None,
    agc_attribute: str | None = "user_data",
    chunk_points: int = DEFAULT_CHUNK_POINTS,
    bucket_points: int = DEFAULT_BUCKET_POINTS,
    batch_pulses: int = DEFAULT_BATCH_PULSES,
    progress: bool = False,
) -> IngestResult:
    """Stream one LAS waveform file into a Parquet pulse table (one row per pulse).

    Parameters
    ----------
    las_path : path
        LAS 1.3/1.4 file with waveform packets (formats 4, 5, 9, 10).
    out : path
        Output Parquet file (written atomically).
    dataset : str, optional
        Dataset name of every row (default: the LAS file stem).
    trajectory : path, optional
        Trajectory CSV (``gps_time, x, y, z``); fills ``sensor_*`` and ``range_m``.
    nominal_range_m : float, optional
        Without a trajectory: put the sensor this many metres before the first echo.
    agc_attribute : str or None
        Point (or extra-bytes) dimension holding the AGC.
    chunk_points, bucket_points, batch_pulses : int
        Streaming sizes (see :class:`waveforest.io.las.read.WaveformPulseReader`).
    progress : bool
        Show a progress bar on stderr.
    """
    from tqdm import tqdm

    las_path, out = Path(las_path), Path(out)
    locate, sensor = sensor_locator(trajectory, nominal_range_m)
    refuse_overwriting_input(out, las_path)

    output_folder(out)  # refuse a device, FIFO or directory before reading anything
    reader = WaveformPulseReader(
        las_path,
        dataset=dataset,
        agc_attribute=agc_attribute,
        locate=locate,
        chunk_points=chunk_points,
        bucket_points=bucket_points,
        batch_pulses=batch_pulses,
        tmp_dir=out.parent,
    )
    with tqdm(
        total=reader.n_passes * reader.las.n_points,
        unit="pt",
        unit_scale=True,
        disable=not progress,
        file=sys.stderr,
        desc=f"ingest {las_path.name}",
    ) as bar:
        reader.on_points = bar.update
        batches = iter(reader)
        try:
            n = write_pulse_batches(with_rate(batches, bar), out)
        finally:
            batches.close()  # on failure too: removes spilled buckets and unmaps now, not at GC
    st = reader.stats
    return IngestResult(
        out=out,
        n_pulses=n,
        n_points=st.n_points,
        n_without_waveform=st.n_without_waveform,
        n_split_pulses=st.n_split_pulses,
        n_bad_gps=st.n_bad_gps,
        n_bad_geometry=st.n_bad_geometry,
        agc_attribute=st.agc_dimension,
        sensor=sensor,
        las=reader.las,
    )
