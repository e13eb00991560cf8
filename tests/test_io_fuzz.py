"""Byte-level fuzzing of the real RIEGL file through ``waveforest info`` and ``ingest``.

A seeded list of mutations of ``tests/data/real/riegl_fwf.las`` (and its ``.wdp``): bit
flips, overwrites with 0x00 / 0xFF / random bytes, truncations, and overwrites of the
fields that steer a reader (counts, offsets, lengths, scales, descriptor fields, point
wave packet fields, GPS times) with 0, 1, maxima, NaN, infinities and near misses. Each
case runs both commands through ``waveforest.cli.main`` in a long-lived worker process
(one import for all cases; killed and replaced when a case hangs or the worker dies)
and must end in one of two ways:

- exit 0; or
- exit 1 with exactly one ``waveforest: error:`` line that names the input file,

with no Python traceback, no hang (:data:`CASE_TIMEOUT_S`), no death by a signal, every
warning naming the file it is about, and, when ingest fails, no output or temporary file
left and the previous output of the same name intact. :data:`CASES_FAST` cases run by
default (:data:`PINNED_FAST` extremes and the start of the seeded list); under
``-m slow``, every header field at its extremes and :data:`CASES_ALL` seeded cases.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import random
import resource
import select
import shutil
import struct
import subprocess
import sys
import traceback
from pathlib import Path

import pytest
from reference_io import RIEGL

SEED = 20250625
CASES_ALL = 400
CASES_FAST = 40
CASE_TIMEOUT_S = 60.0
"""Both commands of one case; they take ~0.2 s on the 170 kB file."""
WORKER_MEMORY_BYTES = 6 << 30
"""Address-space limit of the worker: a runaway allocation fails fast instead of swapping."""
PREVIOUS = b"previous output"

HEADER_END, POINTS_START = 375, 10071
"""The RIEGL file: 375-byte LAS 1.4 header, VLRs up to byte 10071, then 2,535 points of 63 bytes."""
RECORD = 63
N_POINTS = 2535

# (position, struct format) of the public header fields that steer a reader
HEADER_FIELDS = {
    "global_encoding": (6, "<H"),
    "version_minor": (25, "<B"),
    "header_size": (94, "<H"),
    "offset_to_point_data": (96, "<I"),
    "number_of_vlrs": (100, "<I"),
    "point_format": (104, "<B"),
    "point_record_length": (105, "<H"),
    "legacy_point_count": (107, "<I"),
    "scale_x": (131, "<d"),
    "scale_z": (147, "<d"),
    "offset_y": (163, "<d"),
    "max_x": (179, "<d"),
    "start_of_waveform_data": (227, "<Q"),
    "start_of_first_evlr": (235, "<Q"),
    "number_of_evlrs": (243, "<I"),
    "point_count": (247, "<Q"),
    "points_by_return_1": (255, "<Q"),
}
# (offset in a point record, struct format) of format 9 fields
POINT_FIELDS = {
    "X": (0, "<i"),
    "Z": (8, "<i"),
    "return_bits": (14, "<B"),
    "user_data": (17, "<B"),
    "scan_angle": (18, "<h"),
    "gps_time": (22, "<d"),
    "wavepacket_index": (30, "<B"),
    "wavepacket_offset": (31, "<Q"),
    "wavepacket_size": (39, "<I"),
    "return_location": (43, "<f"),
    "x_t": (47, "<f"),
    "z_t": (55, "<f"),
    "amplitude": (59, "<H"),
}
# (offset in a waveform packet descriptor body, struct format)
WPD_FIELDS = {
    "bits_per_sample": (0, "<B"),
    "compression": (1, "<B"),
    "number_of_samples": (2, "<I"),
    "temporal_spacing": (6, "<I"),
    "gain": (10, "<d"),
    "offset": (18, "<d"),
}
# (offset in a VLR header, struct format)
VLR_FIELDS = {"user_id": (2, "16s"), "record_id": (18, "<H"), "record_length": (20, "<H"), "description": (22, "32s")}
# (offset in an extra-bytes descriptor, struct format)
EB_FIELDS = {"data_type": (2, "<B"), "options": (3, "<B"), "name": (4, "32s"), "scale": (112, "<d"), "description": (160, "32s")}
EB_BODY = 9633 + 54
"""Body of the RIEGL file's extra-bytes VLR (two 192-byte descriptors)."""


def _vlr_positions(raw: bytes) -> list[int]:
    pos, out = HEADER_END, []
    for _ in range(struct.unpack_from("<I", raw, 100)[0]):
        out.append(pos)
        pos += 54 + struct.unpack_from("<H", raw, pos + 20)[0]
    return out


def _values(rng: random.Random, fmt: str, original) -> list:
    """Hostile values for a field of struct format ``fmt``."""
    if fmt.endswith("s"):
        size = int(fmt[:-1])
        return [
            b"\xff" * size,
            b"\0" * size,
            bytes([rng.randrange(0x80, 0x100)]) + original[1:],
            original[:3] + bytes([rng.randrange(256)]) + original[4:],
        ]
    if fmt[-1] in "df":
        return [float("nan"), float("inf"), -float("inf"), 0.0, 1e300 if fmt[-1] == "d" else 3e38, -original, original * 2]
    bits = struct.calcsize(fmt) * 8
    signed = fmt[-1].islower()
    lo, hi = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if signed else (0, 2**bits - 1)
    near = [v for v in (original - 1, original + 1, original * 2, original // 2) if lo <= v <= hi]
    return [0, 1, hi, lo, rng.randint(lo, hi), *near]


def make_case(rng: random.Random, raw: bytes, wdp_size: int) -> tuple[str, list[tuple]]:
    """One mutation: a description and a list of operations on (las, wdp) bytes.

    Operations: ``("las", pos, bytes)``, ``("wdp", pos, bytes)``, ``("cut_las", n)``,
    ``("cut_wdp", n)``.
    """
    vlrs = _vlr_positions(raw)
    kind = rng.choices(
        ["header", "vlr", "wpd", "eb", "point", "flip", "overwrite", "truncate", "wdp", "two"],
        weights=[20, 8, 8, 4, 20, 12, 10, 8, 4, 6],
    )[0]
    if kind == "two":  # two mutations at once (e.g. a count and an offset that agree)
        (d1, ops1), (d2, ops2) = make_case(rng, raw, wdp_size), make_case(rng, raw, wdp_size)
        return f"{d1} and {d2}", ops1 + ops2
    if kind == "wdp":  # the .wdp's 60-byte record header
        n = rng.choice([1, 2, 8])
        pos = rng.randrange(0, 60 - n)
        return f"wdp header: {n} bytes of ff at byte {pos}", [("wdp", pos, b"\xff" * n)]

    def field(pos, fmt, name):
        original = struct.unpack_from(fmt, raw, pos)[0]
        value = rng.choice(_values(rng, fmt, original))
        return f"{name} = {value!r}", [("las", pos, struct.pack(fmt, value))]

    if kind == "header":
        name = rng.choice(sorted(HEADER_FIELDS))
        return field(*HEADER_FIELDS[name], name)
    if kind == "vlr":
        k = rng.randrange(len(vlrs))
        name = rng.choice(sorted(VLR_FIELDS))
        off, fmt = VLR_FIELDS[name]
        return field(vlrs[k] + off, fmt, f"VLR {k + 1} {name}")
    if kind == "wpd":
        k = rng.choice([1, 2, 1, 2, 3])  # VLRs 2, 3 hold the descriptors in use
        name = rng.choice(sorted(WPD_FIELDS))
        off, fmt = WPD_FIELDS[name]
        return field(vlrs[k] + 54 + off, fmt, f"descriptor {k} {name}")
    if kind == "eb":
        j = rng.randrange(2)
        name = rng.choice(sorted(EB_FIELDS))
        off, fmt = EB_FIELDS[name]
        return field(EB_BODY + 192 * j + off, fmt, f"extra-bytes descriptor {j + 1} {name}")
    if kind == "point":
        ops, names = [], []
        name = rng.choice(sorted(POINT_FIELDS))
        for _ in range(rng.choice([1, 1, 3, 50])):  # one point, a few, or many
            i = rng.randrange(N_POINTS)
            off, fmt = POINT_FIELDS[name]
            desc, op = field(POINTS_START + i * RECORD + off, fmt, f"point {i} {name}")
            ops += op
            names.append(desc)
        return (names[0] if len(names) == 1 else f"{len(names)} points: {names[0]}, ..."), ops
    region = rng.choice([(0, HEADER_END), (HEADER_END, POINTS_START), (POINTS_START, len(raw))])
    if kind == "flip":
        ops = []
        for _ in range(rng.choice([1, 1, 2, 8])):
            pos, bit = rng.randrange(*region), rng.randrange(8)
            ops.append(("las", pos, bytes([raw[pos] ^ (1 << bit)])))
        return f"{len(ops)} bit flip(s) from byte {ops[0][1]}", ops
    if kind == "overwrite":
        n = rng.choice([1, 2, 4, 8, 16, 64])
        pos = rng.randrange(region[0], region[1] - n)
        fill = rng.choice(["00", "ff", "random"])
        data = bytes(rng.randrange(256) for _ in range(n)) if fill == "random" else bytes.fromhex(fill) * n
        return f"{n} bytes of {fill} at byte {pos}", [("las", pos, data)]
    if rng.random() < 0.25:
        n = rng.randrange(wdp_size)
        return f"wdp truncated to {n} bytes", [("cut_wdp", n)]
    n = rng.randrange(*region)
    return f"truncated to {n} bytes", [("cut_las", n)]


def _extreme(fmt: str, high: bool):
    if fmt[-1] in "df":
        return float("inf") if high else float("nan")
    return 2 ** (struct.calcsize(fmt) * 8) - 1 if high else 0


def pinned(fields: list[str] | None = None) -> list[tuple[str, list[tuple]]]:
    """Every header field at its extremes (all ones and 0; inf and NaN for floats)."""
    out = []
    for name in fields or sorted(HEADER_FIELDS):
        pos, fmt = HEADER_FIELDS[name]
        for high in (True, False) if fields is None else (True,):
            value = _extreme(fmt, high)
            out.append((f"{name} = {value!r}", [("las", pos, struct.pack(fmt, value))]))
    return out


PINNED_FAST = ["number_of_vlrs", "number_of_evlrs", "point_count", "offset_to_point_data", "header_size", "scale_x"]
"""Header fields whose all-ones value the fast subset always tries (a corrupt VLR count once hung)."""


def cases(n: int, fast: bool = False) -> list[tuple[str, list[tuple]]]:
    """Pinned extremes of the header fields, then the first ``n`` cases of the seeded list."""
    rng = random.Random(SEED)
    raw = RIEGL.read_bytes()
    wdp_size = RIEGL.with_suffix(".wdp").stat().st_size
    return pinned(PINNED_FAST if fast else None) + [make_case(rng, raw, wdp_size) for _ in range(n)]


def apply(ops: list[tuple], folder: Path) -> Path:
    """Write the mutated copy of the RIEGL file (and its .wdp) into ``folder``."""
    folder.mkdir(parents=True)
    las, wdp = bytearray(RIEGL.read_bytes()), bytearray(RIEGL.with_suffix(".wdp").read_bytes())
    for op in ops:
        if op[0] in ("las", "wdp"):
            buf = las if op[0] == "las" else wdp
            buf[op[1] : op[1] + len(op[2])] = op[2]
        elif op[0] == "cut_las":
            del las[op[1] :]
        else:
            del wdp[op[1] :]
    path = folder / "fuzzed.las"
    path.write_bytes(las)
    path.with_suffix(".wdp").write_bytes(wdp)
    return path


# -- the worker ---------------------------------------------------------------------------


def _invoke(argv: list[str]) -> dict:
    """Run ``waveforest.cli.main(argv)`` in this process; its exit code, output, traceback."""
    from waveforest.cli import main

    out, err, tb, code = io.StringIO(), io.StringIO(), None, 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        except BaseException:  # any escape is what the fuzz looks for
            code, tb = None, traceback.format_exc()
    return {"code": code, "out": out.getvalue(), "err": err.getvalue(), "traceback": tb}


def worker() -> None:
    """Read one JSON request a line on stdin, answer one JSON line on the original stdout."""
    resource.setrlimit(resource.RLIMIT_AS, (WORKER_MEMORY_BYTES, WORKER_MEMORY_BYTES))
    answers = os.fdopen(os.dup(1), "w")
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)  # nothing else may write into the answer channel
    for line in sys.stdin:
        req = json.loads(line)
        result = {
            "info": _invoke(["info", req["las"]]),
            "ingest": _invoke(["ingest", req["las"], "--out", req["out"], "--no-progress"]),
        }
        answers.write(json.dumps(result) + "\n")
        answers.flush()


class Worker:
    """A worker process started by the test; replaced after a hang or a death."""

    def __init__(self, log: Path):
        self.log = log
        self.proc = None

    def _start(self) -> None:
        code = f"import sys; sys.path[:0] = [{str(Path(__file__).parent)!r}]; import test_io_fuzz; test_io_fuzz.worker()"
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=log
            )

    def run(self, las: Path, out: Path) -> dict | str:
        """The worker's answer, or ``"hang"`` / ``"died: ..."``."""
        if self.proc is None or self.proc.poll() is not None:
            self._start()
        self.proc.stdin.write((json.dumps({"las": str(las), "out": str(out)}) + "\n").encode())
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], CASE_TIMEOUT_S)
        line = self.proc.stdout.readline() if ready else b""
        if line:
            return json.loads(line)
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
            return "hang"
        rc = self.proc.returncode
        return f"died: exit status {rc}" + (" (killed by a signal)" if rc < 0 else "")

    def close(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def problems(result: dict | str, las: Path, out: Path) -> list[str]:
    """What is wrong with the outcome of one case (empty: handled cleanly)."""
    if isinstance(result, str):
        return [result]
    found = []
    names = (las.name, las.with_suffix(".wdp").name)
    for cmd in ("info", "ingest"):
        r = result[cmd]
        if r["traceback"]:
            found.append(f"{cmd}: uncaught {r['traceback'].strip().splitlines()[-1]}")
            continue
        if "Traceback" in r["err"]:
            found.append(f"{cmd}: traceback on stderr")
        if r["code"] not in (0, 1):
            found.append(f"{cmd}: exit status {r['code']}")
        errors = [ln for ln in r["err"].splitlines() if ln.startswith("waveforest: error:")]
        if r["code"] == 1 and (len(errors) != 1 or not any(n in errors[0] for n in names)):
            found.append(f"{cmd}: exit 1 without one error line naming the file: {r['err'].strip()[-300:]!r}")
        if r["code"] == 0 and errors:
            found.append(f"{cmd}: error line but exit 0")
        stray = [
            ln for ln in r["err"].splitlines()
            if ln.strip() and not ln.startswith(("waveforest: warning:", "waveforest: error:"))
        ]
        if stray:
            found.append(f"{cmd}: stray stderr line {stray[0][:200]!r}")
        notes = [ln for ln in r["err"].splitlines() if ln.startswith("waveforest: warning:")]
        notes += [ln for ln in r["out"].splitlines() if ln.startswith("note:")]
        unnamed = [ln for ln in notes if not any(n in ln for n in names)]
        if unnamed:
            found.append(f"{cmd}: warning that names no file: {unnamed[0][:200]!r}")
    listing = sorted(os.listdir(out.parent))
    if result["ingest"]["code"] == 1:
        if listing != [out.name] or out.read_bytes() != PREVIOUS:
            found.append(f"ingest failed but left {listing} (previous output {'intact' if out.read_bytes() == PREVIOUS else 'changed'})")
    elif result["ingest"]["code"] == 0 and listing != [out.name]:
        found.append(f"ingest succeeded but left {listing}")
    return found


def _fuzz(tmp_path: Path, n: int, fast: bool) -> None:
    worker = Worker(tmp_path / "worker.log")
    failures = []
    todo = cases(n, fast)
    try:
        for k, (desc, ops) in enumerate(todo):
            case = tmp_path / f"case{k:04d}"
            las = apply(ops, case / "in")
            out = case / "out" / "pulses.parquet"
            out.parent.mkdir()
            out.write_bytes(PREVIOUS)
            found = problems(worker.run(las, out), las, out)
            if found:
                failures.append(f"case {k} ({desc}): " + "; ".join(found))
            else:
                shutil.rmtree(case)
    finally:
        worker.close()
    assert not failures, f"{len(failures)} of {len(todo)} mutated files mishandled:\n" + "\n".join(failures)


def test_fuzz_fast(tmp_path):
    _fuzz(tmp_path, CASES_FAST - len(PINNED_FAST), fast=True)


@pytest.mark.slow
def test_fuzz_all(tmp_path):
    _fuzz(tmp_path, CASES_ALL, fast=False)


def test_fuzz_catches_a_hang_and_a_traceback(tmp_path):
    """The harness itself: a hang, a death and an escaped exception are each reported."""
    las = tmp_path / "x.las"
    out = tmp_path / "out" / "p.parquet"
    out.parent.mkdir()
    out.write_bytes(PREVIOUS)
    clean = {"code": 0, "out": "", "err": "", "traceback": None}
    assert problems("hang", las, out) == ["hang"]
    escaped = {"info": clean, "ingest": dict(clean, code=None, traceback="Traceback ...\nIndexError: boom")}
    assert problems(escaped, las, out) == ["ingest: uncaught IndexError: boom"]
    unnamed = {"info": dict(clean, code=1, err="waveforest: error: something\n"), "ingest": clean}
    assert "without one error line naming the file" in problems(unnamed, las, out)[0]
    (out.parent / ".p.parquet.abc.part").write_bytes(b"")
    left = {"info": clean, "ingest": dict(clean, code=1, err="waveforest: error: x.las: bad\n")}
    assert "left" in problems(left, las, out)[0]
