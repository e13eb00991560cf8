"""Gaussian decomposition: speed against scipy's curve_fit, accuracy against truth and the
Cramér–Rao bound, and first-echo ranges against the sensor's discrete returns.

Usage: ``python benchmarks/decompose.py [--n 20000] [--reference 300] [--las F.las ...]
[--baseline REV]``. Prints ``name: value unit``.

- **speed**: waveforms per CPU second per core (Numba with 1 thread, and with both cores: the
  process's CPU time, so a loaded machine costs wall time but not the figure) on the bundled
  RIEGL file's waveforms and the first ``--las-pulses`` of each ``--las`` file (noise from the
  waveforms' tails, no pulse width: what ``waveforest decompose`` does without ``--cfd``), and
  on synthetic ALS60-like waveforms (1-ns sampling, FWHM 7 ns given, 160 samples, 1-3 echoes);
  with ``--baseline REV`` the ``sensor/decompose.py`` of git revision REV on the same waveforms
  in the same run (``*_baseline`` lines); ``scipy.optimize.curve_fit`` of the same Gaussian
  model started from the true parameters, on ``--reference`` of the synthetic waveforms.
- **accuracy** on the synthetic waveforms (noise SD 1.3 DN; echoes of 5-40 SD, 1-3 FWHM
  apart): recall and precision (a found echo within one SD of a true one), range RMSE of
  isolated echoes against the Cramér–Rao bound for their amplitude, width, noise and sampling
  (the Fisher information of Eq. F1 at the true parameters), and the amplitude bias.
- **ranges on the RIEGL file** (and on ``--las`` files): the share of pulses whose first decomposed echo lies within
  0.10 m of the first discrete return, beside the tuned CFD's (``tune-cfd``).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

import numba
import numpy as np
import pyarrow as pa

from waveforest.constants import RANGE_PER_NS
from waveforest.io.las.read import WaveformPulseReader
from waveforest.model.decompose import noise_and_width
from waveforest.model.self_tuning import Pulses
from waveforest.sensor.decompose import decompose

ROOT = Path(__file__).resolve().parents[1]
RIEGL = ROOT / "tests" / "data" / "real" / "riegl_fwf.las"
SD, FWHM, DT, N_SAMPLES = 1.3, 7.0, 1.0, 160
S = FWHM / (2 * math.sqrt(2 * math.log(2)))


def out(name: str, value, unit: str = "", fmt: str = ".4g") -> None:
    print(f"{name}: {value:{fmt}} {unit}".rstrip(), flush=True)


def synthetic(n: int, seed: int = 1):
    """Waveforms (n, N_SAMPLES) with 1-3 echoes each, and their true (A, mu) lists."""
    rng = np.random.default_rng(seed)
    t = np.arange(N_SAMPLES) * DT
    x = 10.0 + rng.normal(0.0, SD, (n, N_SAMPLES))
    truth = []
    for i in range(n):
        k = int(rng.integers(1, 4))
        mus = 15.0 + np.cumsum(rng.uniform(FWHM, 3 * FWHM, k))
        amps = rng.uniform(5, 40, k) * SD
        for a, mu in zip(amps, mus):
            x[i] += a * np.exp(-0.5 * ((t - mu) / S) ** 2)
        truth.append(list(zip(amps, mus)))
    return x, truth


def rate(fn, n: int, threads: int, repeat: int = 3) -> tuple[float, float]:
    """Waveforms per CPU second and per wall second of ``fn()`` on ``n`` waveforms with
    ``threads`` Numba threads (best of ``repeat``)."""
    numba.set_num_threads(threads)
    fn()  # compiled and warm
    cpu, wall = zip(*(_timed(fn) for _ in range(repeat)))
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return n / min(cpu), n / min(wall)


def _timed(fn) -> tuple[float, float]:
    c0, t0 = time.process_time(), time.perf_counter()
    fn()
    return time.process_time() - c0, time.perf_counter() - t0


def baseline_decompose(rev: str):
    """``decompose`` of ``src/waveforest/sensor/decompose.py`` at git revision ``rev``."""
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:src/waveforest/sensor/decompose.py"],
                         check=True, capture_output=True, text=True).stdout
    mod = types.ModuleType(f"decompose_{rev}")
    exec(compile(src.replace("cache=True", "cache=False"), f"decompose@{rev}", "exec"), mod.__dict__)
    return mod.decompose


def first_batch(path: Path, n: int):
    """The first ``n`` pulses of a waveform file, its noise (tails) and the waveform arrays."""
    reader = iter(WaveformPulseReader(path, agc_attribute=None, batch_pulses=n))
    batch = next(reader)
    reader.close()
    mean, sd, _, _ = noise_and_width(None, batch)
    p = Pulses.of(batch)
    return p.samples, p.lengths, p.sampling_ns, mean, sd


def speeds(name: str, fn_args: tuple, kwargs: dict, versions: dict) -> None:
    n = len(fn_args[0])
    cores = min(2, numba.config.NUMBA_NUM_THREADS)
    for tag, dec in versions.items():
        fn = functools.partial(dec, *fn_args, **kwargs)
        cpu1, _ = rate(fn, n, 1)
        cpu2, wall2 = rate(fn, n, cores)
        out(f"waveforms_per_cpu_s_{name}_1_thread{tag}", cpu1, "/s", ".0f")
        out(f"waveforms_per_cpu_s_per_core_{name}_{cores}_threads{tag}", cpu2, "/s", ".0f")
        out(f"waveforms_per_wall_s_{name}_{cores}_threads{tag}", wall2, "/s", ".0f")


def crb_range_m(amplitude: float) -> float:
    """Cramér–Rao bound of an isolated echo's centre, as range (m): white noise SD, sampling DT,
    amplitude, centre and width estimated jointly (the centre decouples from the other two)."""
    return math.sqrt(2.0 * SD ** 2 * DT * S / (amplitude ** 2 * math.sqrt(math.pi))) * RANGE_PER_NS


def curve_fit_rate(x, truth, m: int) -> float:
    from scipy.optimize import curve_fit

    t = np.arange(N_SAMPLES) * DT

    def model(tt, *p):
        return sum(p[3 * j] * np.exp(-0.5 * ((tt - p[3 * j + 1]) / p[3 * j + 2]) ** 2) for j in range(len(p) // 3))

    t0 = time.perf_counter()
    for i in range(m):
        p0 = [v for a, mu in truth[i] for v in (a, mu, S)]
        curve_fit(model, t, x[i] - 10.0, p0=p0)
    return m / (time.perf_counter() - t0)


def accuracy(x, truth) -> None:
    d = decompose(x, None, DT, 10.0, SD, pulse_fwhm_ns=FWHM)
    hit = found = true = 0
    err, crb, amp_rel = [], [], []
    for i, row in enumerate(truth):
        t = d.time_ns[i, : d.n_echoes[i]]
        found += len(t)
        true += len(row)
        for a, mu in row:
            j = int(np.argmin(np.abs(t - mu))) if len(t) else -1
            if j >= 0 and abs(t[j] - mu) < S:
                hit += 1
                others = [m2 for _, m2 in row if m2 != mu]
                if all(abs(m2 - mu) > 3 * FWHM for m2 in others):  # isolated: the bound applies
                    err.append((t[j] - mu) * RANGE_PER_NS)
                    crb.append(crb_range_m(a))
                    amp_rel.append(d.amplitude[i, j] / a - 1.0)
    out("recall", hit / true, "", ".4f")
    out("precision", hit / found, "", ".4f")
    rmse, bound = float(np.sqrt(np.mean(np.square(err)))), float(np.sqrt(np.mean(np.square(crb))))
    out("range_rmse_isolated", 100 * rmse, "cm")
    out("range_crb_isolated", 100 * bound, "cm")
    out("range_rmse_over_crb", rmse / bound, "")
    out("amplitude_bias_isolated", 100 * float(np.mean(amp_rel)), "%")
    out("n_isolated_echoes", len(err), "", "d")


def file_pulses(path: Path = RIEGL) -> Pulses:
    return Pulses.of(pa.concat_tables(list(WaveformPulseReader(path, agc_attribute=None))))


def dr_ranges(p: Pulses, path: Path = RIEGL, name: str = "riegl") -> None:
    """Share of pulses with a DR echo whose first decomposed echo is within 0.10 m of it; the
    tuned CFD's share from ``tune-cfd`` on the same file."""
    with tempfile.TemporaryDirectory() as tmp:
        pq, js = Path(tmp) / "p.parquet", Path(tmp) / "cfd.json"
        for argv in (["ingest", str(path), "--out", str(pq)], ["tune-cfd", str(pq), "--out", str(js), "--no-progress"]):
            subprocess.run([str(Path(sys.executable).with_name("waveforest")), *argv], check=True, capture_output=True)
        cfd = json.loads(js.read_text())
    d = decompose(p.samples, p.lengths, p.sampling_ns, cfd["noise_mean"], cfd["noise_sd"], pulse_fwhm_ns=cfd["fwhm_ns"])
    has = np.isfinite(p.dr_time_ns) & (d.n_echoes > 0)
    res = (d.time_ns[has, 0] - p.dr_time_ns[has]) * RANGE_PER_NS
    n_dr = int(np.isfinite(p.dr_time_ns).sum())
    out(f"{name}_within_0_10_m_decomposition", 100 * float(np.sum(np.abs(res) <= 0.10)) / n_dr, "%", ".1f")
    out(f"{name}_median_residual_decomposition", 100 * float(np.median(res)), "cm", ".2f")
    # a constant offset is the sensor's range convention (its DR time of the system pulse), which a
    # range calibration removes, as tune-cfd's range correction does for the CFD
    shifted = res - np.median(res)
    out(f"{name}_within_0_10_m_decomposition_offset_removed", 100 * float(np.sum(np.abs(shifted) <= 0.10)) / n_dr,
        "%", ".1f")
    out(f"{name}_within_0_10_m_cfd", 100 * cfd["within_0_10_m"], "%", ".1f")
    out(f"{name}_no_echo_decomposition", int(np.sum(np.isfinite(p.dr_time_ns) & (d.n_echoes == 0))), "pulses", "d")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=20000, help="synthetic waveforms")
    ap.add_argument("--reference", type=int, default=300, help="waveforms fitted by curve_fit")
    ap.add_argument("--las", type=Path, nargs="*", default=[],
                    help="more waveform files for the speed and DR-range checks (e.g. a virtual campaign's)")
    ap.add_argument("--las-pulses", type=int, default=20000, help="pulses of each --las file timed")
    ap.add_argument("--baseline", help="git revision whose decomposition is timed beside this one")
    args = ap.parse_args()
    x, truth = synthetic(args.n)
    p = file_pulses()
    versions = {"": decompose}
    if args.baseline:
        versions["_baseline"] = baseline_decompose(args.baseline)
        out(f"baseline_{args.baseline}", 1, "", "d")
    mean, sd, _, _ = noise_and_width(None, pa.concat_tables(list(WaveformPulseReader(RIEGL, agc_attribute=None))))
    speeds("riegl", (p.samples, p.lengths, p.sampling_ns, mean, sd), {}, versions)
    for path in args.las:
        speeds(path.stem, first_batch(path, args.las_pulses), {}, versions)
    speeds("synthetic", (x, None, DT, 10.0, SD), {"pulse_fwhm_ns": FWHM}, versions)
    out("waveforms_per_s_curve_fit_synthetic", curve_fit_rate(x, truth, args.reference), "/s", ".0f")
    accuracy(x, truth)
    dr_ranges(p)
    for path in args.las:
        dr_ranges(file_pulses(path), path, path.stem)


if __name__ == "__main__":
    main()
