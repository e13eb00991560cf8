"""Benchmark of the diagnose stage: search on the toy study, and simulation costs of the real chain.

Usage::

    python benchmarks/diagnose.py                       # toy search only
    python benchmarks/diagnose.py RESULTS CONFIG        # + the real chain on a results folder
                                                          (select, features, calibration, campaign)

Prints ``name: value unit`` lines. With a results folder it times one simulation of all the
diagnosed pulses under the base model (vegetation built), one under a vegetation effect
(new plants) and one under a sensor effect (cached plants), and projects the wall time of
one search round (fits on diagnose.fit_pulses pulses per dataset x species, tests on all)
for that study and for the default study (config/config.yaml: 5 comparison datasets x 3
species, ~800 comparison pulses, 6 samples per species and year) from the per-pulse and
per-scene costs.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from waveforest.diagnose.gap import FEATURES
from waveforest.diagnose.search import SearchSettings, search
from waveforest.effects import CATALOGUE

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test fixtures live in tests/fixtures
from fixtures.study import SyntheticStudy


def toy() -> None:
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    real = study.real({"hotspot": 1.3, "clumping": 0.3})
    t = time.perf_counter()
    res = search(study.keys, real, study.simulate, SearchSettings(features=FEATURES, rounds=3, n_boot=200, replicates=2), seed=3)
    print(f"toy_search_two_effects: {time.perf_counter() - t:.2f} s")
    print(f"toy_search_simulations: {res.n_simulations} count")


def real_chain(results: Path, config_path: Path) -> None:
    from waveforest import config
    from waveforest.diagnose.strata import pulse_keys
    from waveforest.diagnose.twins import StudySimulator
    from waveforest.io.pulses import read_pulses
    from waveforest.io.tables import read_datasets, read_fields
    from waveforest.sensor.calibration import load_calibration
    from waveforest.settings import diagnose_settings
    from waveforest.stages.diagnose import with_added_strata

    settings = diagnose_settings(config.load(config_path))
    ds = [d for d in settings.datasets if (results / "select" / f"{d}.parquet").exists()]
    sel = {d: read_pulses(results / "select" / f"{d}.parquet") for d in ds}
    cals = {d: load_calibration(results / "calibration" / f"{d}.json", results / "calibration" / f"{d}.parquet")
            for d in ds}
    cal = {d: (c, c.meta) for d, c in cals.items()}
    if settings.strata.below_crown or settings.strata.ring_m is not None:
        sel = with_added_strata(sel, [results / "agc" / f"{d}.parquet" for d in ds],
                                read_fields(results / "campaign" / "fields.csv"),
                                results / "campaign" / "datasets.csv", cal, settings.strata)
    sim = StudySimulator(sel, read_datasets(results / "campaign" / "datasets.csv"), cal, settings)
    keys = pulse_keys(sel, settings.strata)
    cap = settings.fit_pulses
    n, n_samples = len(keys), keys["sample_id"].nunique()
    n_fit = n if cap is None else len(pulse_keys(sel, settings.strata, int(cap)))
    sim(keys.head(5), {}, 0)  # compile
    timings = {}
    for label, eff in (("base", {}), ("vegetation_effect", {"clumping": 0.3}), ("sensor_effect", {"trigger_loss": 0.1})):
        built = sim.scenes.built
        t = time.perf_counter()
        sim(keys, eff, 1)
        timings[label] = time.perf_counter() - t
        print(f"simulation_{label}: {timings[label]:.2f} s")
        print(f"simulation_{label}_scenes_built: {sim.scenes.built - built} count")
    print(f"diagnosed_pulses: {n} count")
    print(f"fit_pulses: {n_fit} count")
    print(f"diagnosed_samples: {n_samples} count")
    print(f"n_rays: {settings.simulate.mcrt.n_rays} rays")
    per_pulse = timings["sensor_effect"] / n
    per_scene = max(timings["vegetation_effect"] - timings["sensor_effect"], 0.0) / max(n_samples, 1)
    print(f"trace_render_per_pulse: {1000 * per_pulse:.2f} ms")
    print(f"scene_per_sample: {1000 * per_scene:.1f} ms")
    s = settings.search
    fits_per_candidate = len(s.folds) * (s.values - 1 + s.refine) / 2  # full-study equivalents
    tests_per_candidate = len(s.folds) / 2
    n_veg = sum(CATALOGUE[c].stage == "vegetation" for c in s.candidates)
    n_other = len(s.candidates) - n_veg

    def round_s(pulses, fit_pulses, samples):
        def one(p):
            return n_other * per_pulse * p + n_veg * (per_pulse * p + per_scene * samples)
        return fits_per_candidate * one(fit_pulses) + tests_per_candidate * one(pulses)

    print(f"projected_round_this_study: {round_s(n, n_fit, n_samples):.0f} s")
    default_pulses, default_samples = 800, 3 * 2 * 6
    default_fit = min(default_pulses, 5 * 3 * int(cap or 60))
    print(f"projected_round_default_study: {round_s(default_pulses, default_fit, default_samples):.0f} s")


if __name__ == "__main__":
    toy()
    if len(sys.argv) == 3:
        real_chain(Path(sys.argv[1]), Path(sys.argv[2]))
