"""Write-to-temporary-then-rename, so that a failed step leaves no half-written output.

Every output of every stage goes through :func:`atomic_path` (or, for writers that
assemble several temporaries, :func:`output_folder` and :func:`make_temp`), so the rules
hold everywhere: an output may only replace a regular file (never a directory, device,
FIFO or socket: ``--out /dev/full`` run as root must not replace the device); a missing
folder is created; and a folder or file that cannot be made or written is one
:class:`.errors.WaveforestError` naming the path, not a traceback.

A command that writes a folder writes it whole or not at all (:class:`OutputFolder`): into a
hidden sibling ``.NAME.*.part`` that replaces the folder at the end, with a manifest
(:data:`MANIFEST`) naming what the command wrote, so that a folder holding anything else is
refused (:class:`FolderNotOursError`) rather than replaced. Several files written together
are published together by :func:`output_files`.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import shutil
import signal
import stat
import tempfile
import threading
from collections.abc import Iterator, Sequence
from contextvars import ContextVar
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
        pending = _PENDING.get()
        if pending is None:
            publish(tmp, path)
        else:  # inside output_files: published with the others at its end
            pending.append((tmp, path))
            tmp = None
    finally:
        if tmp is not None and tmp.exists():
            tmp.unlink()


_PENDING: ContextVar[list | None] = ContextVar("waveforest_pending_outputs", default=None)
"""The (temporary, path) pairs of :func:`atomic_path` waiting for the end of :func:`output_files`."""


@contextlib.contextmanager
def output_files() -> Iterator[None]:
    """Publish every :func:`atomic_path` output of the block together, at its end.

    On a clean exit all are renamed onto their paths (Ctrl-C and SIGTERM held off meanwhile);
    on any exception none is, their temporaries are removed, and every earlier file of those
    names is left as it was.
    """
    pending: list = []
    token = _PENDING.set(pending)
    try:
        yield
        with _signals_held():
            for tmp, path in pending:
                publish(tmp, path)
    finally:
        _PENDING.reset(token)
        with _signals_held():
            for tmp, _ in pending:
                if tmp.exists():
                    tmp.unlink()


_HELD_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Delay SIGINT, SIGTERM and SIGHUP until the block has run (a swap or clean-up is not cut
    in half); the first one that came is then raised again. Main thread only (else a no-op)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, frame: came.append(signum)) for sig in _HELD_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if came:
            signal.raise_signal(came[0])


MANIFEST = ".waveforest"
"""The file in an output folder that lists what the command wrote there: JSON with ``command``
(its name) and ``files`` (every entry, relative POSIX paths, folders ending in ``/``)."""


class FolderNotOursError(WaveforestError):
    """An output folder holds a file the command did not write (``--force`` replaces it anyway)."""

    def __init__(self, path: Path, name: str, n_more: int, command: str, writer: str | None = None):
        shown = str(path) if str(path).endswith(os.sep) else f"{path}{os.sep}"
        more = f" (and {n_more} more)" if n_more else ""
        by = f" ({writer} did)" if writer and writer != command else ""
        super().__init__(f"{shown}: holds {name}{more}, which {command} did not write{by}; "
                         f"use --force to replace it")
        self.path, self.name, self.command = path, name, command


def _entries(folder: Path) -> list[str]:
    """Every file and folder under ``folder`` (symlinks not followed), relative, folders with ``/``."""
    out = []
    for root, dirs, files in os.walk(folder, onerror=_raise):
        rel = Path(root).relative_to(folder)
        out += [(rel / d).as_posix() + "/" for d in dirs] + [(rel / f).as_posix() for f in files]
    return sorted(out)


def _raise(exc: OSError) -> None:
    raise exc


def _manifest(folder: Path) -> tuple[str | None, set]:
    """The command and entries of ``folder``'s manifest; ``(None, set())`` if none can be read."""
    try:
        data = json.loads((folder / MANIFEST).read_text())
        return str(data["command"]), {str(f) for f in data["files"]}
    except (OSError, ValueError, TypeError, KeyError):
        return None, set()


class OutputFolder:
    """An output folder that a command writes whole or not at all.

    Made at the start of the command: ``path`` is checked at once (before the work), so an
    existing folder holding anything the command did not write (an entry missing from its
    :data:`MANIFEST` by ``command``) is a :class:`FolderNotOursError` unless ``force``; a
    ``path`` that exists and is not a folder is a :class:`WaveforestError`.
    ``with folder as tmp:`` yields a new empty folder ``.NAME.*.part`` beside ``path`` to
    write into; on a clean exit the manifest is added, ``path`` is checked again and ``tmp``
    replaces it (a symlink to a folder: its target is replaced). On any exception (Ctrl-C, and
    SIGTERM as ``waveforest.cli.main`` raises it) ``tmp`` and the folders made for it are
    removed and ``path`` is left as it was. ``inputs``: files the command reads; a folder that
    holds one is refused even with ``force`` (replacing it would delete the input), and so is an
    existing folder this process may not write in.
    """

    def __init__(self, path: str | os.PathLike, command: str, *, force: bool = False,
                 inputs: Sequence[str | os.PathLike] = ()):
        self.path = Path(path)
        self.command = command
        self.force = force
        self.inputs = [Path(os.path.realpath(p)) for p in inputs]
        self.tmp: Path | None = None
        self._target = Path(os.path.realpath(self.path))
        self._made: list[Path] = []
        if self._target.parent == self._target:
            raise WaveforestError(f"{self.path}: cannot be an output folder (give a folder below it)")
        self.check()

    def check(self) -> None:
        """Refuse ``path`` as above (:class:`FolderNotOursError`, :class:`WaveforestError`)."""
        try:
            mode = os.stat(self._target).st_mode
        except (FileNotFoundError, NotADirectoryError):  # absent (its parents are made, or fail, later)
            return
        except OSError as exc:
            raise WaveforestError(f"{self.path}: cannot use as an output folder ({_reason(exc)})") from exc
        if not stat.S_ISDIR(mode):
            raise WaveforestError(f"{self.path}: exists and is not a folder; refusing to replace it "
                                  "(give a folder path)")
        inside = [p for p in self.inputs if p.is_relative_to(self._target)]
        if inside:
            raise WaveforestError(f"{self.path}: holds the input {inside[0].relative_to(self._target)}, which "
                                  f"replacing the folder would delete; give another output folder")
        if not os.access(self._target, os.W_OK | os.X_OK):
            raise WaveforestError(f"{self.path}: cannot write in the output folder (permission denied)")
        if self.force:
            return
        writer, ours = _manifest(self._target)
        if writer != self.command:  # another command's output is not this one's to replace
            ours = set()
        if writer is not None:
            ours.add(MANIFEST)
        try:
            foreign = [e for e in _entries(self._target) if e not in ours]
        except OSError as exc:
            raise WaveforestError(f"{self.path}: cannot read the output folder ({_reason(exc)})") from exc
        foreign = sorted((e for e in foreign if not any(f.endswith("/") and e.startswith(f) and f != e
                                                        for f in foreign)),
                         key=lambda e: (e.startswith("."), e))
        if foreign:  # a foreign folder is named by itself, not by each file in it; visible names first
            raise FolderNotOursError(self.path, foreign[0], len(foreign) - 1, self.command, writer)

    def final(self, path: str | os.PathLike) -> Path:
        """Where ``path`` (under the temporary folder) will be once published."""
        return self.path / Path(path).relative_to(self.tmp)

    def __enter__(self) -> Path:
        parent = self._target.parent
        missing = [p for p in (parent, *parent.parents) if not p.exists()][::-1]
        try:
            for p in missing:
                p.mkdir()
                self._made.append(p)
            self.tmp = Path(tempfile.mkdtemp(prefix=f".{self._target.name}.", suffix=".part", dir=parent))
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(self.tmp, 0o777 & ~umask)  # mkdtemp makes 0700; outputs are ordinary folders
        except OSError as exc:
            self._clean()
            raise WaveforestError(f"{self.path}: cannot create the output folder ({_reason(exc)})") from exc
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> None:
        with _signals_held():
            if exc_type is not None:
                self._clean()
                return
            try:
                entries = [e for e in _entries(self.tmp) if e != MANIFEST]
                (self.tmp / MANIFEST).write_text(json.dumps({"command": self.command, "files": entries},
                                                            indent=1) + "\n")
                self.check()
                self._swap()
            except BaseException:
                self._clean()
                raise
            self._made = []

    def _swap(self) -> None:
        """Rename ``tmp`` onto the folder (an existing folder first moved aside, then removed)."""
        target, old = self._target, None
        try:
            if os.path.lexists(target):
                old = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".old", dir=target.parent))
                old.rmdir()
                os.replace(target, old)
            try:
                os.replace(self.tmp, target)
            except BaseException:
                if old is not None:
                    os.replace(old, target)
                raise
        except OSError as exc:
            raise WaveforestError(f"{self.path}: cannot replace the output folder ({_reason(exc)})") from exc
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def _clean(self) -> None:
        """Remove the temporary folder and the folders made for it."""
        if self.tmp is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
        for p in reversed(self._made):
            with contextlib.suppress(OSError):
                p.rmdir()
        self._made = []


def plain(v, *, keep_inf: bool = False):
    """``v`` as plain JSON/YAML values, recursively.

    NumPy scalars become Python values and arrays lists, tuples lists, dict keys strings;
    NaN becomes None, and so do infinities unless ``keep_inf`` (YAML writes them ``.inf``).
    """
    if isinstance(v, np.ndarray):
        v = v.tolist()
    elif isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v) and not (keep_inf and math.isinf(v)):
        return None
    if isinstance(v, dict):
        return {str(k): plain(x, keep_inf=keep_inf) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain(x, keep_inf=keep_inf) for x in v]
    return v


def write_json(obj, path: str | os.PathLike) -> Path:
    """Write ``obj`` as indented JSON, atomically; NaN and infinities are written as null."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(plain(obj), indent=2, allow_nan=False) + "\n")
    return path
