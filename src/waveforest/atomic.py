"""Write-to-temporary-then-rename, so that a failed step leaves no half-written output.

Every output of every stage goes through :func:`atomic_path` (or, for writers that
assemble several temporaries, :func:`output_folder` and :func:`make_temp`), so the rules
hold everywhere: an output may only replace a regular file (never a directory, device,
FIFO or socket: ``--out /dev/full`` run as root must not replace the device); a missing
folder is created; and a folder or file that cannot be made or written is one
:class:`.errors.WaveforestError` naming the path, not a traceback.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from waveforest.errors import WaveforestError

_KINDS = {
    stat.S_ISDIR: "a directory",
    stat.S_ISCHR: "a character device",
    stat.S_ISBLK: "a block device",
    stat.S_ISFIFO: "a FIFO (named pipe)",
    stat.S_ISSOCK: "a socket",
}
_OUTPUT_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS}
"""Errors of a write that are the output's whatever file they name (disk full, read-only)."""


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def output_folder(path: str | os.PathLike) -> Path:
    """Check that ``path`` may be written as an output and create its folder; return ``path``.

    Raises
    ------
    WaveforestError
        If ``path`` exists and is not a regular file (following symlinks), or its folder
        cannot be created (a file in the way, no permission).
    """
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):  # absent (the folder is made, or fails, below)
        mode = None
    except OSError as exc:
        raise WaveforestError(f"{path}: cannot use as an output ({_reason(exc)})") from exc
    if mode is not None and not stat.S_ISREG(mode):
        kind = next((name for test, name in _KINDS.items() if test(mode)), "not a regular file")
        raise WaveforestError(f"{path}: the output exists and is {kind}; refusing to replace it (give a file path)")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise WaveforestError(f"{path}: cannot create the output folder {path.parent} ({_reason(exc)})") from exc
    if not path.parent.is_dir():
        raise WaveforestError(f"{path}: cannot create the output folder {path.parent} (not a directory)")
    return path


def make_temp(beside: str | os.PathLike, suffix: str = ".part") -> Path:
    """Create an empty hidden temporary file beside ``beside`` (after :func:`output_folder`)."""
    beside = output_folder(beside)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{beside.name}.", suffix=suffix, dir=beside.parent)
    except OSError as exc:
        raise WaveforestError(f"{beside}: cannot create a file in {beside.parent} ({_reason(exc)})") from exc
    os.close(fd)
    return Path(name)


def publish(tmp: Path, path: Path) -> None:
    """Give ``tmp`` the permissions of a new file and rename it onto ``path``."""
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; outputs are ordinary files
        output_folder(path)  # nothing non-regular appeared there meanwhile
        os.replace(tmp, path)
    except OSError as exc:
        raise WaveforestError(f"{path}: cannot write the output ({_reason(exc)})") from exc


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    On any exception (and on SIGTERM, which ``waveforest.cli.main`` turns into one) the
    temporary file is removed and ``path`` is left untouched (an existing file of that name
    is not lost). An ``OSError`` of writing the output (disk full, read-only, or any
    error naming the temporary file) becomes a
    :class:`WaveforestError` naming ``path``.

    Raises
    ------
    WaveforestError
        See :func:`output_folder`, and the write errors above.
    """
    path = Path(path)
    tmp = make_temp(path)
    try:
        try:
            yield tmp
        except OSError as exc:
            if exc.errno in _OUTPUT_ERRNOS or exc.filename in (str(tmp), tmp):
                raise WaveforestError(f"{path}: cannot write the output ({_reason(exc)})") from exc
            raise
        publish(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _plain(v):
    """``v`` with NumPy scalars as Python values and non-finite floats as None, recursively."""
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def write_json(obj, path: str | os.PathLike) -> Path:
    """Write ``obj`` as indented JSON, atomically; NaN and infinities are written as null."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_plain(obj), indent=2, allow_nan=False) + "\n")
    return path
