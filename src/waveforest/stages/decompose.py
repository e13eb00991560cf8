"""The ``decompose`` stage: a waveform file -> an echo point cloud (:mod:`waveforest.model.decompose`)."""

from __future__ import annotations

import click

from waveforest.cliutil import EXISTING_FILE, OUT_FILE, warnings_to_stderr
from waveforest.model.decompose import DecomposeSettings, decompose_file

DEFAULTS = DecomposeSettings()


@click.command("decompose")
@click.argument("las_file", type=EXISTING_FILE)
@click.option("--out", "out", type=OUT_FILE, required=True,
              help="Echo point cloud: .laz (compressed) or .las, LAS 1.4 point format 6 (or 9) with extra bytes; "
                   "a summary JSON is written beside it (OUT.json).")
@click.option("--cfd", "cfd", type=EXISTING_FILE, default=None,
              help="CFD or calibration JSON (`waveforest tune-cfd` or `calibrate`): noise and the system "
                   "pulse FWHM (the narrowest echo). Default: noise from the waveforms' tails, free widths.")
@click.option("--min-snr", type=click.FloatRange(min=0, min_open=True), default=DEFAULTS.min_snr, show_default=True,
              help="Detection level: an echo's amplitude in noise SDs.")
@click.option("--max-echoes", type=click.IntRange(1, 15), default=DEFAULTS.max_echoes, show_default=True,
              help="Most echoes per waveform (1-15).")
@click.option("--fixed-width", is_flag=True, help="Every echo has the system pulse's width (needs --cfd).")
@click.option("--calibration-constant", type=click.FloatRange(min=0, min_open=True), default=None,
              help="C_cal of the backscatter cross-section (docs/method.md, Eq. F2); without it the "
                   "cross-section is relative, scaled to 1000 m.")
@click.option("--trajectory", type=EXISTING_FILE, default=None,
              help="Trajectory CSV (gps_time,x,y,z): sensor positions, hence ranges and cross-sections.")
@click.option("--nominal-range", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Without a trajectory: the sensor this many metres before the first echo.")
@click.option("--point-format", type=click.Choice(["6", "9"]), default="6", show_default=True,
              help="9 keeps the waveforms: each echo points into its pulse's packet, copied to a .wdp "
                   "beside OUT (LAS 1.4 point format 9).")
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
def decompose(las_file, out, cfd, min_snr, max_echoes, fixed_width, calibration_constant, trajectory,
              nominal_range, point_format, progress):
    """Decompose every waveform into Gaussian echoes: an echo point cloud (docs/method.md §(f2)).

    Per echo: range, amplitude, width, energy and the backscatter cross-section.

    Waveforms that are flat, all noise or too short are flagged and counted in the summary;
    they give no echo. Clipped waveforms and fits that did not converge or fit poorly keep
    their echoes, flagged and counted. Only the first waveform packet of a pulse is
    decomposed; pulses with more are counted. Without a trajectory or --nominal-range the
    ranges and cross-sections are unknown (written as 0, the dimensions' no_data value).

    Example:

    \b
    waveforest decompose flight.las --out echoes.laz --cfd cfd.json --nominal-range 1000
    waveforest decompose flight.las --out echoes.las --point-format 9   # + echoes.wdp
    """
    if out.suffix.lower() not in (".las", ".laz"):
        raise click.BadParameter(f"{out}: expected a .las or .laz output file", param_hint="'--out'")
    if fixed_width and cfd is None:
        raise click.BadParameter("needs --cfd (the system pulse width)", param_hint="'--fixed-width'")
    settings = DecomposeSettings(min_snr=min_snr, max_echoes=max_echoes, fixed_width=fixed_width,
                                 calibration_constant=calibration_constant, point_format=int(point_format))
    with warnings_to_stderr():
        s = decompose_file(las_file, out, settings, cfd_path=cfd, trajectory=trajectory,
                           nominal_range_m=nominal_range, progress=progress)
    flagged = ", ".join(f"{name} {n:,}" for name, n in s.flags.items()) or "none"
    several = (f" ({s.n_pulses_several_packets:,} with returns in several waveform packets, each decomposed)"
               if s.n_pulses_several_packets else "")
    click.echo(f"decompose: {s.n_pulses:,} pulses{several}, {s.n_echoes:,} echoes "
               f"({s.n_packets / max(s.seconds, 1e-9):,.0f} waveforms/s); flagged: {flagged} -> {s.out}")
