"""What every subcommand shares: --config, --seed, --threads; path types; multi-value options;
warnings shown as one line each."""

from __future__ import annotations

import contextlib
import functools
import sys
import warnings
from pathlib import Path

import click
import numba
from tqdm import tqdm

from waveforest import config as _config
from waveforest.atomic import FolderNotOursError

EXISTING_FILE = click.Path(exists=True, dir_okay=False, path_type=Path)
"""An input file that must exist."""
OUT_FILE = click.Path(dir_okay=False, path_type=Path)
"""An output file (written atomically by the stage)."""
OUT_DIR = click.Path(file_okay=False, path_type=Path)
"""An output folder."""
EXISTING_DIR = click.Path(exists=True, file_okay=False, path_type=Path)
"""An input folder that must exist."""


def _set_threads(threads: int | None) -> None:
    if threads:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def stage_options(func):
    """Add ``--config``, ``--seed`` and ``--threads``; pass the loaded config as ``cfg``.

    ``--config`` must name an existing file; ``--seed`` (>= 0) overrides the config's master
    seed; ``--threads`` must be >= 1 (more than Numba's threads are capped). A bad config ends
    in one :class:`~waveforest.config.ConfigError` naming where the bad value came from: the
    config file (``file: key path: expected``) or the option (``--seed: ...``).
    """

    @click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False), default=None,
                  help="Study config YAML (default: built-in defaults).")
    @click.option("--seed", type=click.IntRange(min=0), default=None,
                  help="Master seed of every random draw, an integer >= 0 (default: the config's seed).")
    @click.option("--threads", type=click.IntRange(min=1), default=None,
                  help="Numba threads, 1 or more; capped at the cores available (default: all cores).")
    @functools.wraps(func)
    def wrapper(*args, config_path=None, seed=None, threads=None, **kwargs):
        overrides = None if seed is None else {"seed": seed}
        if overrides is not None:  # an error in the options names the option, not the file
            _config.validate(dict(overrides), source="--seed")
        cfg = _config.load(config_path, overrides=overrides)
        _set_threads(threads)
        return func(*args, cfg=cfg, **kwargs)

    return wrapper


class _Refused(click.ClickException):
    """A refused output folder: a usage error (exit status 2)."""

    exit_code = 2


def force_option(func):
    """Add ``--force``, passed as ``force``: replace an output folder even if it holds files
    the command did not write (:class:`waveforest.atomic.OutputFolder`). Without it such a
    folder is refused with one line naming a file it holds and exit status 2."""

    @click.option("--force", is_flag=True, default=False,
                  help="Replace the output folder even if it holds files this command did not write "
                       "(they are deleted).")
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except FolderNotOursError as exc:
            raise _Refused(str(exc)) from exc

    return wrapper


def input_files_option(flag: str, dest: str, help: str, required: bool = False):
    """An option taking one or more existing files after one flag (:class:`MultiValueOption`;
    the command needs ``cls=MultiValueCommand``), passed as a tuple of Paths under ``dest``."""
    return click.option(flag, dest, cls=MultiValueOption, type=EXISTING_FILE, required=required, help=help)


def dataset_pulses_options(func):
    """Add the inputs of a stage on one dataset's pulse table: the ``PULSES`` argument and
    ``--targets`` / ``--datasets`` (the campaign's targets.csv and datasets.csv), passed as
    ``pulses``, ``targets_csv`` and ``datasets_csv``."""
    func = click.option("--datasets", "datasets_csv", type=EXISTING_FILE, required=True,
                        help="datasets.csv of the campaign.")(func)
    func = click.option("--targets", "targets_csv", type=EXISTING_FILE, required=True,
                        help="targets.csv of the campaign.")(func)
    return click.argument("pulses", type=EXISTING_FILE)(func)


def dataset_fit_options(out_help: str, record: tuple[str, str, str], plot_help: str):
    """Add :func:`dataset_pulses_options`, then the outputs of a stage that fits one dataset:
    ``--out`` (a file; help ``out_help``), a JSON record (``record`` = (flag, dest, help)) and an
    optional ``--plot`` PNG, passed as ``out``, ``record[1]`` and ``plot``."""

    def decorate(func):
        func = click.option("--plot", "plot", type=OUT_FILE, default=None, help=plot_help)(func)
        func = click.option(record[0], record[1], type=OUT_FILE, required=True, help=record[2])(func)
        func = click.option("--out", "out", type=OUT_FILE, required=True, help=out_help)(func)
        return dataset_pulses_options(func)

    return decorate


def reference_sensor_options(outputs: str):
    """Add the options of a study on the reference sensor (docs/method.md §(i2), §(i3)).

    ``--system`` (S(t) Parquet, optional), ``--calibration`` (its JSON, optional), each an
    existing file when given, and ``--out`` (a folder; ``outputs`` names what it receives, for
    the help text) with :func:`force_option`, passed as ``system``, ``calibration``, ``out``
    and ``force``; then :func:`stage_options`.
    """

    def decorate(func):
        func = force_option(stage_options(func))
        func = click.option("--out", type=OUT_DIR, required=True, help=f"Output folder ({outputs}).")(func)
        func = click.option("--calibration", type=EXISTING_FILE, default=None,
                            help="Calibration JSON with noise_mean/noise_sd (default: beside --system).")(func)
        return click.option("--system", type=EXISTING_FILE, default=None,
                            help="The reference dataset's S(t) (config reference_dataset), Parquet; omitted = "
                                 "Gaussian of sensitivity.reference_system.fwhm_ns.")(func)

    return decorate


class MultiValueOption(click.Option):
    """An option that takes one or more values after a single flag (and may also repeat)."""

    def __init__(self, *args, **kwargs):
        kwargs["multiple"] = True
        super().__init__(*args, **kwargs)


class MultiValueCommand(click.Command):
    """A command that rewrites ``--opt a b c`` into ``--opt a --opt b --opt c`` for
    :class:`MultiValueOption` options before click parses the arguments.

    Values are taken until the next token that starts with ``-``; positional arguments must
    therefore come before such an option.
    """

    def parse_args(self, ctx, args):
        flags = {o for p in self.params if isinstance(p, MultiValueOption) for o in p.opts}
        out, current, fresh = [], None, False
        for a in args:
            if a.startswith("-") and a != "-":
                current = a if a in flags else None
                fresh = current is not None
                out.append(a)
                continue
            if current is not None and not fresh:
                out.append(current)
            fresh = False
            out.append(a)
        return super().parse_args(ctx, out)


@contextlib.contextmanager
def warnings_to_stderr():
    """Show every warning once as ``waveforest: warning: ...`` (clear of progress bars)."""

    def show(message, category, filename, lineno, file=None, line=None):
        tqdm.write(f"waveforest: warning: {message}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = show
        yield
