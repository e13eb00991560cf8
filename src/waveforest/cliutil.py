"""Options shared by every subcommand: --config, --seed, --threads."""

from __future__ import annotations

import functools

import click

from . import config as _config


def _set_threads(threads: int | None) -> None:
    if threads:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))


def stage_options(func):
    """Add ``--config``, ``--seed`` and ``--threads``; pass the loaded config as ``cfg``.

    ``--seed`` (>= 0) overrides the config's master seed; ``--threads`` must be >= 1. A bad
    config ends in one :class:`~waveforest.config.ConfigError` (file: key path: expected).
    """

    @click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
                  help="Study config YAML (default: built-in defaults).")
    @click.option("--seed", type=click.IntRange(min=0), default=None, help="Override the config's master seed.")
    @click.option("--threads", type=click.IntRange(min=1), default=None, help="Numba threads (default: all cores).")
    @functools.wraps(func)
    def wrapper(*args, config_path=None, seed=None, threads=None, **kwargs):
        cfg = _config.load(config_path, overrides=None if seed is None else {"seed": seed})
        _set_threads(threads)
        return func(*args, cfg=cfg, **kwargs)

    return wrapper
