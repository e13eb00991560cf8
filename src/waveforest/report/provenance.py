"""What a report was made with: the code, the input data and the machine (:func:`provenance_table`).

- the code: the git commit of the checkout the package runs from, and whether tracked files
  differ from it (``git`` when installed, else the ``.git`` files; no checkout: said so);
- the input data: size and SHA-256 of every campaign file the study reads (:func:`input_files`),
  hashed in chunks, with a progress bar only when hashing takes a while;
- the machine: CPU model, logical cores, memory, operating system.

Nothing here fails the report: what cannot be read is said in its cell.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from waveforest import __version__
from waveforest.errors import WaveforestError
from waveforest.io.las import find_wdp
from waveforest.io.tables import read_datasets
from waveforest.report.markdown import NO_VALUE

CHUNK_BYTES = 1 << 20
"""Bytes read at a time when hashing."""

PROGRESS_DELAY_S = 3.0
"""Seconds of hashing after which a progress bar appears (none for small inputs)."""

GIT_TIMEOUT_S = 10.0
"""Longest wait for one ``git`` call."""

CAMPAIGN_TABLES = ("datasets.csv", "fields.csv", "targets.csv")
"""The campaign tables every study reads."""


@dataclass(frozen=True)
class GitState:
    """The checkout the code runs from. ``root`` None: not a checkout (``note`` says why);
    ``dirty``: tracked files changed since ``commit``, None when unknown."""

    root: Path | None
    commit: str | None = None
    branch: str | None = None
    dirty: int | None = None
    note: str = ""


def checkout_root(package_dir: Path | None = None) -> Path | None:
    """The git checkout holding ``package_dir`` (default: this package's folder); None for an
    installed copy (site-packages) or no ``.git`` above it."""
    start = Path(package_dir or Path(__file__).resolve().parents[1]).resolve()
    if {"site-packages", "dist-packages"} & set(start.parts):
        return None
    for folder in (start, *start.parents):
        if (folder / ".git").exists():
            return folder
    return None


def _git(root: Path, *args: str) -> str:
    env = dict(os.environ, GIT_OPTIONAL_LOCKS="0", LC_ALL="C")  # read only: no index refresh written
    return subprocess.run(["git", "-C", str(root), "--no-optional-locks", *args], capture_output=True, text=True,
                          check=True, timeout=GIT_TIMEOUT_S, env=env).stdout


def _git_dir(root: Path) -> tuple[Path, Path]:
    """(git dir, common dir) of a checkout; a worktree's ``.git`` file points at its git dir."""
    dot = root / ".git"
    gitdir = dot
    if dot.is_file():
        text = dot.read_text().strip()
        if not text.startswith("gitdir:"):
            raise OSError(f"{dot}: no gitdir line")
        gitdir = (root / text[len("gitdir:"):].strip()).resolve()
    common = gitdir
    if (gitdir / "commondir").is_file():
        common = (gitdir / (gitdir / "commondir").read_text().strip()).resolve()
    return gitdir, common


def head_from_files(root: Path) -> tuple[str | None, str | None]:
    """(commit, branch) from the ``.git`` files: HEAD, the loose ref, else ``packed-refs``.
    Branch None when detached; commit None when the ref is not found."""
    gitdir, common = _git_dir(root)
    head = (gitdir / "HEAD").read_text().strip()
    if not head.startswith("ref:"):
        return head or None, None
    ref = head[len("ref:"):].strip()
    branch = ref.removeprefix("refs/heads/")
    for base in (gitdir, common):
        if (base / ref).is_file():
            return (base / ref).read_text().strip() or None, branch
    packed = common / "packed-refs"
    if packed.is_file():
        for line in packed.read_text().splitlines():
            parts = line.split()
            if len(parts) == 2 and parts[1] == ref:
                return parts[0], branch
    return None, branch


def git_state(root: Path | None = None, use_git: bool = True) -> GitState:
    """The commit and changes of the checkout ``root`` (default: :func:`checkout_root`).

    ``git`` (read-only calls) when installed and ``use_git``; else the ``.git`` files (changes
    unknown). Never raises.
    """
    root = checkout_root() if root is None else Path(root)
    if root is None or not (root / ".git").exists():
        return GitState(None, note="not a git checkout")
    if use_git and shutil.which("git"):
        try:
            commit = _git(root, "rev-parse", "HEAD").strip()
            branch = _git(root, "rev-parse", "--abbrev-ref", "HEAD").strip()
            changed = _git(root, "status", "--porcelain", "--untracked-files=no").splitlines()
            return GitState(root, commit, None if branch == "HEAD" else branch, len(changed), "git")
        except (OSError, subprocess.SubprocessError) as exc:
            why = f"git failed ({type(exc).__name__})"
    else:
        why = "git not found"
    try:
        commit, branch = head_from_files(root)
    except (OSError, UnicodeDecodeError) as exc:
        return GitState(root, note=f"{why}; .git unreadable ({exc})")
    return GitState(root, commit, branch, None, f"read from .git; {why}")


def code_text(state: GitState) -> str:
    """One line: the package version and the commit, branch and changes of ``state``."""
    if state.root is None:
        return f"waveforest {__version__} from {Path(__file__).resolve().parents[1]}: {state.note}, no commit to name"
    if state.commit is None:
        return f"waveforest {__version__} from the git checkout {state.root}: commit unknown ({state.note})"
    text = f"waveforest {__version__} from the git checkout {state.root}: commit {state.commit}"
    if state.branch:
        text += f" (branch {state.branch})"
    if state.dirty is None:
        return text + f"; uncommitted changes unknown ({state.note})"
    if state.dirty:
        return text + f"; uncommitted changes in {state.dirty} tracked file{'s' if state.dirty != 1 else ''}"
    return text + "; no uncommitted changes in tracked files"


def input_files(campaign: Path, datasets) -> list[Path]:
    """The campaign files a study of ``datasets`` reads, in reading order: the campaign tables,
    then per dataset its LAS file (and the ``.wdp`` beside it), then its trajectory; then the
    virtual campaign's ``truth.json`` (the report's seed and effects) when present.

    Names come from ``datasets.csv`` (``las_file``, ``trajectory_file``); a dataset it does not
    name, or an unreadable table, falls back to the virtual campaign's names. Files may be missing.
    """
    campaign = Path(campaign)
    try:
        table = read_datasets(campaign / "datasets.csv")
        rows = {str(r["dataset"]): r for r in table.to_dict("records")}
    except (WaveforestError, OSError):
        rows = {}
    out = [campaign / name for name in CAMPAIGN_TABLES]
    for ds in datasets:
        row = rows.get(str(ds), {})
        las = campaign / _name(row.get("las_file"), f"{ds}.las")
        out.append(las)
        wdp = find_wdp(las)
        if wdp is not None:
            out.append(wdp)
        out.append(campaign / _name(row.get("trajectory_file"), f"{ds}_trajectory.csv"))
    if (campaign / "truth.json").is_file():
        out.append(campaign / "truth.json")
    return list(dict.fromkeys(out))


def _name(value, default: str) -> str:
    return value.strip() if isinstance(value, str) and value.strip() else default


def sha256_files(paths, progress: bool = True) -> dict[Path, str]:
    """SHA-256 (hex) of each existing file of ``paths``, read in :data:`CHUNK_BYTES` chunks; a
    bar over all bytes on stderr appears after :data:`PROGRESS_DELAY_S` s (``progress``)."""
    from tqdm import tqdm

    files = [Path(p) for p in paths if Path(p).is_file()]
    total = sum(p.stat().st_size for p in files)
    out = {}
    with tqdm(total=total, unit="B", unit_scale=True, desc="report: SHA-256 of the inputs", file=sys.stderr,
              delay=PROGRESS_DELAY_S, mininterval=1.0, disable=not progress) as bar:
        for p in files:
            h = hashlib.sha256()
            with open(p, "rb") as fh:
                while chunk := fh.read(CHUNK_BYTES):
                    h.update(chunk)
                    bar.update(len(chunk))
            out[p] = h.hexdigest()
    return out


def _size_text(n: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit} ({n:,} bytes)"
    return f"{n:,} bytes"


def _read(path: str) -> str:
    try:
        with open(path, encoding="utf-8", errors="replace") as fh:
            return fh.read()
    except OSError:
        return ""


def cpu_model() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``, macOS ``sysctl``), else the architecture."""
    for line in _read("/proc/cpuinfo").splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("model name", "Model", "Hardware", "cpu model") and value.strip():
            return value.strip()
    if sys.platform == "darwin":
        try:
            return subprocess.run(["sysctl", "-n", "machdep.cpu.brand_string"], capture_output=True, text=True,
                                  check=True, timeout=GIT_TIMEOUT_S).stdout.strip() or platform.machine()
        except (OSError, subprocess.SubprocessError):
            pass
    return platform.processor() or platform.machine() or "unknown"


def memory_bytes() -> int | None:
    """Total physical memory, bytes (``/proc/meminfo``, else ``sysconf``); None when unknown."""
    for line in _read("/proc/meminfo").splitlines():
        if line.startswith("MemTotal:"):
            return int(line.split()[1]) * 1024
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


def os_text() -> str:
    """The operating system: distribution (``/etc/os-release``), kernel and architecture."""
    name = ""
    for line in _read("/etc/os-release").splitlines():
        if line.startswith("PRETTY_NAME="):
            name = line.split("=", 1)[1].strip().strip('"')
    if sys.platform == "darwin":
        name = f"macOS {platform.mac_ver()[0]}"
    kernel = f"{platform.system()} {platform.release()} {platform.machine()}".strip()
    return f"{name}; {kernel}" if name else kernel


def machine() -> dict[str, str]:
    """CPU, logical cores (and those this process may use), memory and OS, as text."""
    cores = os.cpu_count()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else cores
    core_text = NO_VALUE if cores is None else str(cores)
    if cores is not None and usable is not None and usable != cores:
        core_text += f" ({usable} usable by this process)"
    mem = memory_bytes()
    return {"CPU": cpu_model(), "logical cores": core_text,
            "memory": NO_VALUE if mem is None else f"{mem / 2**30:.1f} GiB", "OS": os_text()}


def provenance_table(campaign: Path, datasets, progress: bool = True, state: GitState | None = None
                     ) -> pd.DataFrame:
    """One table, columns item, value, sha256: the code (:func:`code_text`), the machine
    (:func:`machine`), then each input file of :func:`input_files` with its size and SHA-256
    (``— (missing)`` when absent). ``state``: the code's git state (default: :func:`git_state`)."""
    state = git_state() if state is None else state
    rows = [("code", code_text(state), NO_VALUE)]
    rows += [(k, v, NO_VALUE) for k, v in machine().items()]
    paths = input_files(campaign, datasets)
    try:
        digests = sha256_files(paths, progress)
    except OSError as exc:
        digests, why = {}, f"unreadable: {exc}"
    else:
        why = "missing"
    for p in paths:
        if p in digests:
            rows.append((str(p), _size_text(p.stat().st_size), digests[p]))
        else:
            rows.append((str(p), f"{NO_VALUE} ({why if p.is_file() else 'missing'})", NO_VALUE))
    return pd.DataFrame(rows, columns=["item", "value", "sha256"])
