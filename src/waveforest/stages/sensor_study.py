"""The ``sensor-study`` stage: Fig. 9 (:mod:`waveforest.analysis.sensor_study`) and its files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click

from waveforest.analysis.sensor_study import FEATURES, run_sensor_study
from waveforest.atomic import OutputFolder, atomic_path
from waveforest.cliutil import reference_sensor_options
from waveforest.report import plots
from waveforest.sensor.reference import reference_sensor
from waveforest.settings import sensor_study_settings


@dataclass(frozen=True)
class SensorStudySummary:
    table: Path
    figure: Path
    features_table: Path
    n_settings: int
    n_pulses: int
    source: str


def run(out_dir, cfg: dict, system_path=None, calibration_path=None, progress: bool = True,
        threads: int | None = None, scene_builder=None, *, force: bool = False) -> SensorStudySummary:
    """The ``sensor-study`` stage: writes sensor_study.csv, sensor_study_features.csv, fig9.png.

    sensor_study.csv: parameter, value, is_default, level (1-pulse / 5-pulse), scheme
    (resubstitution / cross_validated), accuracy, kappa, n (items classified).
    sensor_study_features.csv: parameter, value, species, n, mean and SD of Apeak, FWHM, E.
    The folder is written whole or not at all (:class:`waveforest.atomic.OutputFolder`).
    """
    folder = OutputFolder(out_dir, "sensor-study", force=force)
    st = sensor_study_settings(cfg)
    ref = reference_sensor(st.reference, system_path, calibration_path, st.range_m)
    result = run_sensor_study(st, ref, progress, threads, scene_builder)
    with folder as out:
        paths = {"csv": out / "sensor_study.csv", "feat": out / "sensor_study_features.csv",
                 "png": out / "fig9.png"}
        with atomic_path(paths["csv"]) as tmp:
            result.table.to_csv(tmp, index=False, float_format="%.6g")
        with atomic_path(paths["feat"]) as tmp:
            result.features.to_csv(tmp, index=False, float_format="%.6g")
        plots.fig9_sensor(result.table, paths["png"], species=list(st.heights_m), features=FEATURES)
    return SensorStudySummary(folder.final(paths["csv"]), folder.final(paths["png"]), folder.final(paths["feat"]),
                              result.n_settings, result.n_pulses, ref.source)


@click.command("sensor-study")
@reference_sensor_options("sensor_study.csv, fig9.png")
def sensor_study(system, calibration, out, force, cfg):
    """Divergence, pulse width and sampling vs three-species LDA accuracy (docs/method.md §(i3))."""

    r = run(out, cfg, system_path=system, calibration_path=calibration, force=force)
    click.echo(f"sensor-study: {r.n_settings} settings, {r.n_pulses} simulated pulses -> {r.table}, {r.figure}")
