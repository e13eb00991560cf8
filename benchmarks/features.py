"""Throughput of the waveform-processing kernels (docs/method.md §(f), h; issue 5 target >= 100,000/s/core).

Prints one figure per line as ``name: value unit``:

- cfd_waveforms_per_s_per_core            detect_echoes on 256-sample 1-ns waveforms, 1 thread,
                                          per CPU second (the per-core figure on a shared machine)
- features_waveforms_per_s_per_core       first_echo_features on the same waveforms, idem
- render_pulses_per_s_per_core            render (Eq. 7) of MCRT-like sigma(t) profiles, idem
- *_wall_1_thread, *_wall_all_threads     the same per wall-clock second

Usage: python benchmarks/features.py [--n 100000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from waveforest.sensor import CFDParams, detect_echoes, first_echo_features, gaussian_system_waveform, render

FWHM_PER_SD = 2.0 * np.sqrt(2.0 * np.log(2.0))


def waveforms(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n ALS60-like records: 1-3 Gaussian echoes (vegetation-like widths), noise 10 +- 1.5 DN, 8 bit."""
    rng = np.random.default_rng(seed)
    t = np.arange(256, dtype=np.float32)
    x = np.empty((n, 256), dtype=np.float32)
    block = 8192
    for lo in range(0, n, block):  # blocks of pulses, each vectorised
        m = min(block, n - lo)
        v = 10.0 + 1.5 * rng.standard_normal((m, 256)).astype(np.float32)
        first = rng.uniform(25.0, 35.0, m)
        for k in range(3):
            c = first + k * rng.uniform(6.0, 20.0, m)
            w = rng.uniform(6.0, 14.0, m) / FWHM_PER_SD
            a = rng.uniform(20.0, 150.0, m) * (rng.random(m) < (1.0 if k == 0 else 0.4))
            v += (a[:, None] * np.exp(-0.5 * ((t[None, :] - c[:, None]) / w[:, None]) ** 2)).astype(np.float32)
        x[lo:lo + m] = np.clip(np.rint(v), 0, 255)
    return x, np.full(n, 256, dtype=np.int64)


def best_rate(fn, n: int, repeat: int) -> tuple[float, float]:
    """(items per CPU second, items per wall-clock second), best of ``repeat`` runs.

    The CPU-time rate is the per-core throughput on a shared machine (other jobs stretch the
    wall-clock time but not the CPU time of this process).
    """
    fn()  # warm-up (compilation or cache load)
    cpu, wall = [], []
    for _ in range(repeat):
        c0, w0 = time.process_time(), time.perf_counter()
        fn()
        cpu.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return n / min(cpu), n / min(wall)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100_000, help="waveforms")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    x, lens = waveforms(args.n)
    cfd = CFDParams().resolved(7.2)
    all_threads = numba.get_num_threads()

    numba.set_num_threads(1)
    ech = detect_echoes(x, lens, 1.0, 10.0, 1.5, cfd)
    t_echo = ech.times_ns[:, 0]
    r_cfd = best_rate(lambda: detect_echoes(x, lens, 1.0, 10.0, 1.5, cfd), args.n, args.repeat)
    r_feat = best_rate(lambda: first_echo_features(x, lens, 1.0, t_echo, 10.0, 1.5), args.n, args.repeat)

    rng = np.random.default_rng(1)
    n_r = max(1000, args.n // 50)
    sig = np.zeros((n_r, 800))  # 40 ns of sigma bins, ~60 non-zero (a canopy profile)
    rows = np.repeat(np.arange(n_r), 60)
    sig[rows, rng.integers(100, 700, rows.size)] = rng.exponential(0.002, rows.size)
    system = gaussian_system_waveform(7.2, 1.5e9)
    t0 = np.full(n_r, 8000.0)
    r_render = best_rate(lambda: render(sig, t0, 1200.0, system, 10.0, 1.5, 1.0, np.random.default_rng(2)), n_r,
                         args.repeat)

    numba.set_num_threads(all_threads)
    r_cfd_all = best_rate(lambda: detect_echoes(x, lens, 1.0, 10.0, 1.5, cfd), args.n, args.repeat)

    print(f"cfd_waveforms_per_s_per_core: {r_cfd[0]:.0f} 1/s")
    print(f"features_waveforms_per_s_per_core: {r_feat[0]:.0f} 1/s")
    print(f"render_pulses_per_s_per_core: {r_render[0]:.0f} 1/s")
    print(f"cfd_waveforms_per_s_wall_1_thread: {r_cfd[1]:.0f} 1/s")
    print(f"features_waveforms_per_s_wall_1_thread: {r_feat[1]:.0f} 1/s")
    print(f"cfd_waveforms_per_s_wall_all_threads: {r_cfd_all[1]:.0f} 1/s")
    print(f"threads: {all_threads} count")
    print(f"mean_echoes_per_waveform: {ech.n_echoes.mean():.2f} count")


if __name__ == "__main__":
    main()
