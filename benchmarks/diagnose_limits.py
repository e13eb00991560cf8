"""Detection limits with the whole waveform against the first-echo features alone, on the same data.

Usage::

    python benchmarks/diagnose_limits.py RESULTS[:CONFIG] [--replicates 20] [--candidates understory xy_error]
        [--with H_ground]

RESULTS is a study's results folder (select, features, calibration, agc, campaign,
config/diagnose.yaml, or the config CONFIG). The diagnosis's power analysis
(:func:`waveforest.diagnose.power.detection_limits`: its seeds, pool and calibrated floor) runs
twice on the same simulations, with the first-echo features alone (H, Npeaks, Apeak, FWHM, E)
and with the whole waveform (every statistic of :mod:`waveforest.diagnose.waveform`); ``--with F ...``
adds a third set, the first-echo features and the statistics F (named ``first_echo_F``). Prints
per effect
``limit_<features>_<effect>: value unit`` (``nan`` when not reached up to the strongest value
tried), ``limit_ci_<features>_<effect>: [low, high] unit`` (its 95 % interval, ``nan`` beyond
the strongest value tried), ``power_at_bound_<features>_<effect>: share [low, high]`` (Wilson interval),
``limit_ratio_<set>_<effect>: set / first echo`` (of the distances from off in the search
coordinate u, :mod:`waveforest.diagnose.catalogue`: 0.5 = halved), ``floor_scale_<features>: factor`` and the
wall and CPU time.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path

from diagnose_floor import study_inputs

from waveforest.diagnose import catalogue as cat
from waveforest.diagnose.gap import ALL_FEATURES, FEATURES
from waveforest.diagnose.power import detection_limits
from waveforest.diagnose.waveform import WAVEFORM_FEATURES


def strength(effect: str, value: float) -> float:
    """Distance of ``value`` from the effect's off value in the search coordinate (NaN stays NaN)."""
    return abs(cat.to_u(effect, value) - cat.off_u(effect)) if math.isfinite(value) else math.nan


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", help="results folder, or RESULTS:CONFIG to read another config")
    p.add_argument("--replicates", type=int, default=20, help="pseudo-real replicates per value")
    p.add_argument("--candidates", nargs="*", default=None, help="effects (default: the diagnosis's)")
    p.add_argument("--with", dest="extra", nargs="*", default=(), choices=WAVEFORM_FEATURES,
                   help="whole-waveform statistics of a third set beside the first-echo features")
    a = p.parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    r, _, c = a.results.partition(":")
    settings, keys, _, simulate = study_inputs(Path(r), Path(c) if c else None)
    power = replace(settings.power, replicates=a.replicates)
    search = settings.search if a.candidates is None else replace(settings.search, candidates=tuple(a.candidates))
    limits = {}
    sets = {"first_echo": FEATURES, "whole_waveform": ALL_FEATURES}
    if a.extra:
        sets["first_echo_" + "_".join(a.extra)] = FEATURES + tuple(a.extra)
    for name, features in sets.items():
        cal: dict = {}
        lim, _ = detection_limits(keys, simulate, replace(search, features=features), power, settings.seed,
                                  calibration=cal)
        print(f"floor_scale_{name}: {cal['floor'].scale:.3f} factor")
        for row in lim.itertuples():
            print(f"limit_{name}_{row.effect}: {row.smallest_detectable:.4g} {row.unit}")
            print(f"limit_ci_{name}_{row.effect}: [{row.limit_ci_low:.4g}, {row.limit_ci_high:.4g}] {row.unit}")
            print(f"power_at_bound_{name}_{row.effect}: {row.power_at_bound:.2f} "
                  f"[{row.power_at_bound_ci_low:.2f}, {row.power_at_bound_ci_high:.2f}] at {row.upper_bound:.4g}")
        limits[name] = lim.set_index("effect")
    for name in list(sets)[1:]:
        for effect in limits["first_echo"].index:
            ratio = (strength(effect, limits[name].loc[effect].smallest_detectable)
                     / strength(effect, limits["first_echo"].loc[effect].smallest_detectable))
            print(f"limit_ratio_{name}_{effect}: {ratio:.3f} set/first_echo")
    print(f"pulses: {len(keys)} count")
    print(f"samples: {keys['sample_id'].nunique()} count")
    print(f"wall_time: {time.perf_counter() - t0:.1f} s")
    print(f"cpu_time: {time.process_time() - c0:.1f} s")


if __name__ == "__main__":
    main()
