"""Timings of the analysis stages; prints ``name: value unit`` lines.

Run ``python benchmarks/analysis.py [--rays 30000 8000] [--pulses 16]``. Figures:

* ``select_rate``: pulses per second through :func:`select.select_pulses` (KD-tree matching);
* ``classify_time``: one dataset's LDA (resubstitution + grouped CV, two levels);
* ``build_<species>``, ``prepare_<species>``: one vegetation instance and its Embree BVH;
  ``trace_<species>_<rays>``: MCRT per pulse; ``render_<species>``: Eq. 7 + CFD per pulse;
  ``simulate_<species>_<rays>``: the cost of ``simulate``, per pulse plus per instance (a
  sample's pool has ``simulate.instances_per_sample`` of them).
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
import pandas as pd
import pyarrow as pa


def _select_rate(n: int = 200_000, n_fields: int = 2000) -> float:
    from waveforest.model.selection import SelectRules, select_pulses

    rng = np.random.default_rng(0)
    fx, fy = rng.uniform(0, 5000, n_fields), rng.uniform(0, 5000, n_fields)
    fields = pd.DataFrame(dict(sample_id=[f"s{i}" for i in range(n_fields)], year=2010, species="raspberry",
                               functional_group="low_green", x=fx, y=fy, ground_z=0.0, height_m=1.0,
                               radius_m=1.0, is_tree=rng.random(n_fields) < 0.3))
    k = rng.integers(0, n_fields, n)
    ex, ey = fx[k] + rng.normal(0, 1.0, n), fy[k] + rng.normal(0, 1.0, n)
    lists = lambda v: pa.ListArray.from_arrays(pa.array(np.arange(n + 1, dtype=np.int32)), pa.array(v))  # noqa
    table = pa.table({"pulse_id": np.arange(n), "n_echoes": pa.array(np.ones(n, np.int16)),
                      "echo_x": lists(ex), "echo_y": lists(ey), "echo_z": lists(rng.uniform(0, 3, n))})
    t = time.perf_counter()
    select_pulses(table, fields, 2010, SelectRules())
    return n / (time.perf_counter() - t)


def _classify_time() -> float:
    from waveforest import config
    from waveforest.analysis.classify import classify_dataset
    from waveforest.settings import classify_settings

    rng = np.random.default_rng(1)
    groups = ["conifer", "broadleaf", "low_green", "low_barren_abiotic"]
    n = 20_000
    g = rng.integers(0, 4, n)
    samples = [f"s{i}" for i in rng.integers(0, 800, n)]
    df = pd.DataFrame(dict(dataset="d", pulse_id=np.arange(n), source="real", sample_id=samples,
                           species=np.array(["a", "b", "c", "d"])[g], functional_group=np.array(groups)[g],
                           n_echoes=1, E=rng.normal(1000 + 100 * g, 150), Apeak=rng.normal(80 + 10 * g, 12),
                           FWHM=rng.normal(10, 1, n), H=1.0))
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # no sand road here: features stay unnormalised
        classify_dataset(df, classify_settings(config.load()))
    return time.perf_counter() - t


def _simulate(species: str, height: float, rays: int, n: int, cfg: dict) -> dict:
    from waveforest.mcrt import Beams, prepare, trace
    from waveforest.model.forward import render_sigma
    from waveforest.sensor.reference import reference_sensor
    from waveforest.settings import mcrt_setup, reference_system, sensor_setup
    from waveforest.vegetation import build_scene

    build_scene(species, height, 0)  # warm-up (Numba compilation, parameter files)
    t = time.perf_counter()
    scene = build_scene(species, height, 1)
    build = time.perf_counter() - t
    rng = np.random.default_rng(0)
    origin = np.column_stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), np.full(n, 1200.0)])
    beams = Beams.from_divergence(origin, np.tile([0.0, 0.0, -1.0], (n, 1)), 0.15, np.full(n, 1200.0))
    t = time.perf_counter()
    prepared = prepare(scene)
    prep = time.perf_counter() - t
    mcrt = mcrt_setup(cfg, n_rays=rays)
    t = time.perf_counter()
    res = trace(prepared, beams, seed=1, **mcrt.kwargs())
    tr = (time.perf_counter() - t) / n
    ref = reference_sensor(reference_system(cfg))
    setup = sensor_setup(cfg, ref.system, ref.noise_mean, ref.noise_sd, 1.0)
    t = time.perf_counter()
    render_sigma(res.sigma, res.t0_ns, np.full(n, 1200.0), setup, rng)
    rd = (time.perf_counter() - t) / n
    return {"build": build, "prepare": prep, "trace": tr, "render": rd, "triangles": len(scene)}


def main(argv=None) -> None:
    from waveforest import config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, nargs="+", default=[30000, 8000])
    ap.add_argument("--pulses", type=int, default=16)
    args = ap.parse_args(argv)
    cfg = config.load()
    print(f"select_rate: {_select_rate():.0f} pulses/s")
    print(f"classify_time: {_classify_time():.2f} s")
    for species, h in (("birch", 3.5), ("raspberry", 1.2), ("fireweed", 1.5)):
        for rays in args.rays:
            r = _simulate(species, h, rays, args.pulses, cfg)
            if rays == args.rays[0]:
                print(f"build_{species}: {r['build'] * 1e3:.0f} ms")
                print(f"prepare_{species}: {r['prepare'] * 1e3:.0f} ms")
                print(f"triangles_{species}: {r['triangles']} triangles")
                print(f"render_{species}: {r['render'] * 1e3:.2f} ms/pulse")
            print(f"trace_{species}_{rays}: {r['trace'] * 1e3:.1f} ms/pulse")
            per_instance = r["build"] + r["prepare"]
            print(f"simulate_{species}_{rays}: {(r['trace'] + r['render']) * 1e3:.1f} ms/pulse + "
                  f"{per_instance * 1e3:.0f} ms/instance")


if __name__ == "__main__":  # pragma: no cover
    main()
