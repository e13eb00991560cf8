"""The ``sensitivity`` stage: Fig. 8 (:mod:`waveforest.analysis.sensitivity`) and its files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click
import pyarrow as pa

from waveforest.analysis.sensitivity import run_sensitivity
from waveforest.atomic import OutputFolder, atomic_path
from waveforest.cliutil import reference_sensor_options
from waveforest.io.pulses import write_table
from waveforest.report import plots
from waveforest.sensor.reference import reference_sensor
from waveforest.settings import sensitivity_settings


@dataclass(frozen=True)
class SensitivitySummary:
    table: Path
    figure: Path
    pulses_table: Path
    n_settings: int
    pulses: int
    source: str


def run(out_dir, cfg: dict, system_path=None, calibration_path=None, progress: bool = True,
        threads: int | None = None, scene_builder=None, *, force: bool = False) -> SensitivitySummary:
    """The ``sensitivity`` stage: writes sensitivity.csv, sensitivity_baseline.csv,
    sensitivity_pulses.parquet (one row per simulated pulse) and fig8.png.

    sensitivity.csv columns: parameter, value, n_pulses, n_echo, mean_apeak, sd_apeak,
    se_apeak, mean_E, mean_FWHM, mean_H (DN, DN, ns, m), one row per swept setting;
    sensitivity_baseline.csv: the same columns (no value) for the species model as is.
    The folder is written whole or not at all (:class:`waveforest.atomic.OutputFolder`).
    """

    folder = OutputFolder(out_dir, "sensitivity", force=force)
    st = sensitivity_settings(cfg)
    ref = reference_sensor(st.reference, system_path, calibration_path, st.range_m)
    result = run_sensitivity(st, ref, progress, threads, scene_builder)
    table = result.table
    with folder as out:
        paths = {"csv": out / "sensitivity.csv", "base": out / "sensitivity_baseline.csv",
                 "pq": out / "sensitivity_pulses.parquet", "png": out / "fig8.png"}
        with atomic_path(paths["csv"]) as tmp:
            table[table["parameter"] != "baseline"].to_csv(tmp, index=False, float_format="%.6g")
        with atomic_path(paths["base"]) as tmp:
            table[table["parameter"] == "baseline"].drop(columns="value").to_csv(tmp, index=False,
                                                                                 float_format="%.6g")
        write_table(pa.Table.from_pandas(result.pulses, preserve_index=False), paths["pq"])
        plots.fig8_sensitivity(table, paths["png"], source=ref.source, height_m=st.height_m)
    return SensitivitySummary(folder.final(paths["csv"]), folder.final(paths["png"]), folder.final(paths["pq"]),
                              len(table), st.pulses, ref.source)


@click.command("sensitivity")
@reference_sensor_options("sensitivity.csv, fig8.png")
def sensitivity(system, calibration, out, force, cfg):
    """Sensitivity of simulated birch Apeak to leaf angle, rho, tau and leaf area (docs/method.md §(i2))."""

    r = run(out, cfg, system_path=system, calibration_path=calibration, force=force)
    click.echo(f"sensitivity: {r.n_settings} settings x {r.pulses} pulses -> {r.table}, {r.figure}")
