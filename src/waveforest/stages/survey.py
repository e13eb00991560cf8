"""The ``survey`` stage: fly a user's scene (SCENE.yaml) with a user's flight (SURVEY.yaml).

Builds the tracer settings from the config's ``mcrt`` section (the survey's quality
overrides the ray budget's tolerance, or fixes the rays per pulse, and the highest order) and the ``als60`` preset from its ``sensor`` and
``sensitivity.reference_system`` sections, then calls :func:`waveforest.survey.run_survey`.
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import click

from waveforest.cliutil import EXISTING_FILE, OUT_DIR, force_option, stage_options, warnings_to_stderr
from waveforest.settings import mcrt_setup, reference_system, sensor_settings
from waveforest.survey import load_scene, load_survey, run_survey, sensor_setup, survey_mcrt
from waveforest.survey.scene import input_files


def _part(ctx, param, value: str | None) -> tuple[int, int] | None:
    if value is None:
        return None
    try:
        i, n = (int(v) for v in value.split("/"))
    except ValueError:
        raise click.BadParameter(f"expected I/N with 0 <= I < N, got {value!r}") from None
    if not 0 <= i < n:
        raise click.BadParameter(f"expected I/N with 0 <= I < N, got {value!r}")
    return i, n


@click.command()
@click.argument("scene_file", type=EXISTING_FILE)
@click.argument("survey_file", type=EXISTING_FILE)
@click.option("--out", "out", required=True, type=OUT_DIR, help="Output folder (LAS, .wdp, trajectory, summary).")
@click.option("--part", default=None, callback=_part,
              help="Trace only tiles k with k mod N = I (I/N, e.g. 0/4) and stop before the merge; "
                   "a run without --part merges.")
@click.option("--progress/--no-progress", default=True, help="Progress bar (pulses/s, ETA) on stderr.")
@force_option
@stage_options
def survey(scene_file, survey_file, out, part, progress, force, cfg):
    """Fly a survey over your own scene with multiple scattering and write LAS 1.4 waveform files.

    SCENE_FILE and SURVEY_FILE are YAML files (docs/survey.md; examples/survey/). Random draws
    follow SURVEY_FILE's seed, or --seed where given (the same seed gives the same files);
    --config gives the tracer (mcrt) and the sensor model of the als60 preset. An interrupted run resumes from its completed tiles.

    Example:

    \b
    waveforest survey examples/survey/SCENE.yaml examples/survey/SURVEY.yaml --out my_survey
    """
    with warnings_to_stderr():
        _run(scene_file, survey_file, out, part, progress, force, cfg)


next(p for p in survey.params if p.name == "seed").help = (
    "Master seed of every random draw, an integer >= 0 (default: SURVEY_FILE's seed).")


def _run(scene_file, survey_file, out, part, progress, force, cfg):
    """The command's work (warnings shown as ``waveforest: warning: ...``)."""
    sensor = sensor_settings(cfg)
    sv = load_survey(survey_file, sensor, reference_system(cfg))
    seed = click.get_current_context().params.get("seed")
    if seed is not None:  # --seed overrides the survey file's seed
        sv = replace(sv, seed=int(seed))
    scene = load_scene(scene_file, progress=progress)
    mcrt = survey_mcrt(mcrt_setup(cfg), sv)
    setup = sensor_setup(sv, sensor)
    result = run_survey(scene, sv, mcrt, setup, out, force=force, progress=progress, part=part,
                        inputs=[scene_file, survey_file, *input_files(scene_file, survey_file)])
    if result is None:
        click.echo(f"part {part[0]}/{part[1]}: tiles traced (run without --part to merge into {out})")
    else:
        n, n_rec, n_sat = result["pulses_traced"], result["pulses_recorded"], result["saturated_pulses"]
        silent = f" ({n - n_rec} without a discrete return: no point, so no waveform, in the LAS)" if n_rec < n else ""
        click.echo(f"{out}: {n} pulses, {n_rec} recorded{silent}, {result['returns']} returns, "
                   f"{result['cpu_ms_per_pulse']:.1f} ms CPU per pulse, peak {result['peak_memory_mb']:.0f} MB")
        if n_sat:
            warnings.warn(f"{n_sat} of {n} pulses ({n_sat / n:.0%}) reach the digitiser's full scale "
                          f"({setup.digitizer_max} DN): their waveforms are clipped and their discrete returns "
                          f"early; lower scanner.gain (now {sv.scanner.gain:g}) or fly higher", stacklevel=2)
