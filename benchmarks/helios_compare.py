"""waveforest survey beside HELIOS++ 2.2.2 on the same OBJ scenes and flight, first order.

Not run in CI: it needs a HELIOS++ build (``--helios``, default
/work/helios/build-helios/helios++; recipe in ../shared/tools/helios/). Settings matched as in
that folder's NOTES.md: nadir pulses from an oscillating mirror at 0.0001 deg, 0.15 mrad,
HELIOS's beamSampleQuality Q (``--quality``, default 98: 1 + sum_{r<Q} floor(2 pi r) = 29,816
subrays) and waveforest at the same number of rays per pulse, first order only.

Scenes (OBJ + MTL, ``helios_reflectance`` = rho, read by both tools):

* ``plane``: a 40 x 40 m Lambertian plane (rho 0.5) tilted by ``--tilt`` deg (default 1) about a
  horizontal axis at azimuth 27 deg (HELIOS drops subray returns of equal range, so a level
  plane, or one tilted about a grid axis of its subray pattern, loses energy);
* ``canopy``: ``waveforest.vegetation.build("raspberry", 1.2, 7)`` with its ground, written as
  PLY and converted by :func:`ply2obj`, the whole scene tilted the same way.

HELIOS's energy unit and its waveform's time origin (its pulse shape's peak, bins floored) are
not waveforest's, so both are fixed on the plane (scale and offset of the energy-weighted
range) and then applied to the canopy. Figures (``name: value unit``):

* ``canopy_energy_ratio``: mean first-order energy per pulse, waveforest / HELIOS (scaled on the
  plane; target within 2 %);
* ``canopy_centroid_diff_ns``: mean difference of the energy-weighted one-way echo times, ns
  (target within HELIOS's 0.25-ns bins); ``canopy_centroid_rms_ns``: per matched pulse;
* ``helios_cpu_ms_per_pulse``, ``waveforest_cpu_ms_per_pulse_order1``,
  ``waveforest_cpu_ms_per_pulse_order10`` (the canopy, equal rays; the marginal CPU time per
  pulse between a leg of ``--length`` and one three times as long (``canopy_marginal_pulses_*``
  pulses more), so that scene loading and BVH builds cancel: HELIOS's whole process on one
  thread, waveforest's tiles: trace and sensor twin) and ``speedup_order1``,
  ``order10_over_helios``; ``waveforest_run_cpu_ms_per_pulse_order1``
  and ``speedup_order1_whole_run`` count waveforest's whole survey call (tiles and the merge into
  the LAS, ``.wdp`` and truth files), as HELIOS's figure counts its writing. Energies and centroids are those of the
  long leg;
* with ``--baseline-src SRC`` (the ``src`` folder of another checkout, e.g. a ``git worktree``
  of an earlier commit), waveforest's first order is also flown with that code, in a
  subprocess, on the same legs in the same run: ``baseline_waveforest_cpu_ms_per_pulse_order1``
  and ``speedup_order1_over_baseline``.

    python benchmarks/helios_compare.py [--quality 98] [--length 4] [--tilt 1] [--rate 8000]
        [--baseline-src SRC]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import yaml

from waveforest import config
from waveforest.constants import C_M_PER_NS
from waveforest.scene import Scene, read_ply, write_ply
from waveforest.settings import mcrt_setup, reference_system, sensor_settings
from waveforest.survey import load_scene, load_survey, run_survey, sensor_setup, survey_mcrt
from waveforest.survey.engine import plan
from waveforest.vegetation import build

HELIOS = "/work/helios/build-helios/helios++"
ALTITUDE = 1100.0
SPEED = 40.0
RATE = 8000.0
"""Pulse rate, Hz: at 40 m/s a pulse every 5 mm along the leg, so that the long leg adds 464
pulses over the canopy and its marginal CPU is many times the noise of loading the scene and
building its BVH (at 250 Hz the 15 added pulses left the figure within that noise; at 2000 Hz
the 116 added pulses still moved waveforest's figure by up to 50 % between runs)."""


BASELINE = """import json, sys
from pathlib import Path
sys.path.insert(0, {bench!r})
from helios_compare import run_waveforest
cpu = []
for k, (sub, length) in enumerate({legs!r}):  # the first flight warms Numba's caches up
    d = Path(sub) / f"baseline{{k}}"
    d.mkdir()
    _, e, _, r = run_waveforest(d, Path({obj!r}), {rays}, 1, length, {rate})
    cpu.append((r["cpu_s"], len(e)))
print(json.dumps(cpu[1:]))
"""


def baseline_marginal(src: str, legs: list[tuple[Path, float]], obj: Path, rays: int, rate: float) -> float:
    """waveforest's marginal first-order CPU per pulse (ms) between the last two of ``legs``
    (short, long; the first flown only to load Numba's caches, as the plane does in this
    process) with the code of ``src`` (a checkout's ``src`` folder), in a subprocess."""
    code = BASELINE.format(bench=str(Path(__file__).parent), legs=[(str(d), length) for d, length in legs],
                           obj=str(obj), rays=rays, rate=rate)
    env = {**os.environ, "PYTHONPATH": str(Path(src).resolve())}
    done = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True)
    (c0, n0), (c1, n1) = json.loads(done.stdout.strip().splitlines()[-1])
    return 1000 * (c1 - c0) / (n1 - n0)


def ply2obj(ply: Path, obj: Path) -> Path:
    """A PLY scene (per-face rho, tau, kind) as OBJ + MTL: one Lambertian material per distinct
    rho (``helios_reflectance`` = rho, ``Kd 1 1 1``, ``Ks 0 0 0``); tau has no HELIOS equivalent."""
    sc = read_ply(ply)
    rho = np.round(np.asarray(sc.rho, float) * np.ones(len(sc)), 6)
    values, which = np.unique(rho, return_inverse=True)
    mtl = obj.with_suffix(".mtl")
    with open(mtl, "w") as fh:
        for k, v in enumerate(values):
            fh.write(f"newmtl m{k}\nKd 1 1 1\nKs 0 0 0\nhelios_reflectance {v:.6f}\n")
    tri = sc.triangles.astype(np.float64).reshape(-1, 3)
    with open(obj, "w") as fh:
        fh.write(f"mtllib {mtl.name}\n")
        np.savetxt(fh, tri, fmt="v %.6f %.6f %.6f")
        for k in range(len(values)):
            faces = np.flatnonzero(which == k)
            fh.write(f"usemtl m{k}\n")
            idx = 3 * faces[:, None] + np.arange(1, 4)
            np.savetxt(fh, idx, fmt="f %d %d %d")
    return obj


TILT_AXIS_DEG = 27.0
"""Azimuth of the horizontal tilt axis: not along a grid axis of HELIOS's subray pattern, so no
two subrays hit the plane at exactly the same range (HELIOS keeps only one of equal ranges)."""


def tilt_scene(sc: Scene, deg: float) -> Scene:
    """``sc`` turned by ``deg`` about the horizontal axis at azimuth :data:`TILT_AXIS_DEG` (Rodrigues)."""
    a, b = math.radians(deg), math.radians(TILT_AXIS_DEG)
    u = np.array([math.cos(b), math.sin(b), 0.0])
    k = np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    r = np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k
    return Scene((sc.triangles.astype(np.float64) @ r.T).astype(np.float32), sc.rho, sc.tau, sc.kind)


def subrays(q: int) -> int:
    return 1 + sum(int(math.floor(2 * math.pi * r)) for r in range(1, q))


def helios_files(d: Path, obj: Path, q: int, length: float, rate: float = RATE) -> Path:
    (d / "platform.xml").write_text("""<?xml version="1.0"?>
<document><platform id="sr22" name="Cirrus SR-22" type="linearpath">
<scannerMount z="0.7"><rot axis="x" angle_deg="-90" /><rot axis="z" angle_deg="90" /></scannerMount>
</platform></document>
""")
    (d / "scanner.xml").write_text(f"""<?xml version="1.0"?>
<document><scanner id="wf_als" accuracy_m="0.0" beamDivergence_rad="0.00015" name="wf_als" optics="oscillating"
 pulseFreqs_Hz="{rate:g}" pulseLength_ns="4" rangeMin_m="10" scanAngleMax_deg="30" scanFreqMin_Hz="0"
 scanFreqMax_Hz="200" wavelength_nm="1064" maxNOR="0" receivedEnergyMin_W="1e-15">
 <FWFSettings binSize_ns="0.25" beamSampleQuality="{q}" winSize_ns="1"/></scanner></document>
""")
    (d / "scene.xml").write_text(f"""<?xml version="1.0"?>
<document><scene id="s" name="s"><part><filter type="objloader">
<param type="string" key="filepath" value="{obj}" /><param type="string" key="up" value="z" />
</filter></part></scene></document>
""")
    (d / "survey.xml").write_text(f"""<?xml version="1.0"?>
<document>
<platformSettings id="p" movePerSec_m="{SPEED:g}" z="{ALTITUDE:g}" onGround="false"/>
<scannerSettings id="s" active="true" pulseFreq_hz="{rate:g}" scanAngle_deg="0.0001" scanFreq_hz="50"
 beamDivergence_rad="0.00015"/>
<survey name="cmp" platform="{d / 'platform.xml'}#sr22" scanner="{d / 'scanner.xml'}#wf_als"
 scene="{d / 'scene.xml'}#s">
<FWFSettings binSize_ns="0.25" beamSampleQuality="{q}" winSize_ns="1"/>
<detectorSettings rangeMax_m="2000" accuracy_m="0.0"/>
<leg><platformSettings template="p" x="0" y="{-length / 2:g}"/><scannerSettings template="s"/></leg>
<leg><platformSettings template="p" x="0" y="{length / 2:g}"/><scannerSettings template="s" active="false"/></leg>
</survey></document>
""")
    return d / "survey.xml"


def run_helios(helios: str, survey: Path, out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Run HELIOS++ (one thread); per pulse: origin (n, 3), energy, energy-weighted one-way time (ns); CPU s."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([helios, str(survey), "--writeWaveform", "-j", "1", "--seed", "1", "--output", str(out),
                    "--gpsStartTime", "0"], cwd=survey.parent, check=True, capture_output=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    files = sorted(out.rglob("*fullwave.txt"))
    if not files:
        raise SystemExit(f"HELIOS++ wrote no fullwave file under {out}")
    origins, energy, centroid = [], [], []
    for f in files:
        for line in f.read_text().splitlines():
            v = np.array(line.split(), float)
            tmin, w = v[7], v[10:]
            t = tmin + 0.25 * np.arange(len(w))
            origins.append(v[1:4])
            energy.append(w.sum())
            centroid.append((w * t).sum() / w.sum())
    return np.array(origins), np.array(energy), np.array(centroid), cpu


def run_waveforest(d: Path, obj: Path, rays: int, orders: int, length: float, rate: float = RATE):
    """The same flight through `waveforest survey`; per pulse: origin, energy (order 1), one-way centroid (ns)."""
    (d / "SCENE.yaml").write_text(yaml.safe_dump({"objects": [{"file": str(obj)}], "ground": {"type": "none"}}))
    doc = {"seed": 1, "platform": {"legs": [{"start": [0.0, -length / 2], "end": [0.0, length / 2],
                                             "altitude_m": ALTITUDE + 0.7, "speed_m_s": SPEED}]},
           "scanner": {"preset": "als60", "pulse_rate_hz": rate, "scan_angle_deg": 0.0, "divergence_mrad": 0.15},
           "quality": {"rays_per_pulse": rays, "max_order": orders, "tile_m": 100.0}, "output": {"truth": True}}
    (d / "SURVEY.yaml").write_text(yaml.safe_dump(doc))
    cfg = config.load(None)
    sensor = sensor_settings(cfg)
    sv = load_survey(d / "SURVEY.yaml", sensor, reference_system(cfg))
    sc = load_scene(d / "SCENE.yaml")
    cpu = time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = run_survey(sc, sv, survey_mcrt(mcrt_setup(cfg), sv), sensor_setup(sv, sensor),
                         d / f"out{orders}", threads=1)
    res["run_cpu_s"] = time.process_time() - cpu  # tiles, BVH builds and the merge into the LAS files
    pulses = plan(sc, sv).pulses
    origins, energy, centroid = [], [], []
    for row in pq.read_table(d / f"out{orders}" / "truth.parquet").to_pylist():
        s = np.asarray(row["sigma_order_1"])
        t = row["t0_ns"] + (np.arange(len(s)) + 0.5) * row["bin_ns"]
        origins.append(pulses.origin[row["pulse_id"]])
        energy.append(s.sum())
        centroid.append((s * t).sum() / s.sum() / 2)  # two-way -> one-way
    return np.array(origins), np.array(energy), np.array(centroid), res


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--helios", default=HELIOS)
    ap.add_argument("--quality", type=int, default=98, help="HELIOS beamSampleQuality (subrays = waveforest rays)")
    ap.add_argument("--length", type=float, default=4.0, help="leg length over the scenes, m")
    ap.add_argument("--tilt", type=float, default=1.0, help="tilt of both scenes, deg (>= 0.5)")
    ap.add_argument("--rate", type=float, default=RATE, help=f"pulse rate, Hz (default {RATE:g})")
    ap.add_argument("--baseline-src", help="src folder of another checkout, flown beside this one (first order)")
    a = ap.parse_args(argv)
    rays = subrays(a.quality)
    print(f"rays_per_pulse: {rays} rays")
    with tempfile.TemporaryDirectory(prefix="helios_cmp_") as tmp:
        tmp = Path(tmp)
        plane = Scene(np.array([[[-20, -20, 0], [20, -20, 0], [20, 20, 0]], [[-20, -20, 0], [20, 20, 0], [-20, 20, 0]]],
                               np.float32), 0.5, 0.0, 0)
        write_ply(tilt_scene(plane, a.tilt), tmp / "plane.ply")
        canopy = build("raspberry", 1.2, 7).scene
        write_ply(tilt_scene(canopy, a.tilt), tmp / "canopy.ply")
        print(f"canopy_triangles: {len(canopy)} triangles")
        found, short = {}, {}
        for name in ("plane", "canopy"):
            d = tmp / name
            d.mkdir()
            obj = ply2obj(tmp / f"{name}.ply", d / f"{name}.obj")
            for length, into in ((a.length, short), (3 * a.length, found)):
                sub = d / f"{length:g}"
                sub.mkdir()
                h = run_helios(a.helios, helios_files(sub, obj, a.quality, length, a.rate), sub / "helios")
                w = run_waveforest(sub, obj, rays, 1, length, a.rate)
                into[name] = (h, w)
            print(f"{name}_pulses_helios: {len(found[name][0][1])} pulses")
            print(f"{name}_pulses_waveforest: {len(found[name][1][1])} pulses")
        (hp, wp) = found["plane"]
        scale = wp[1].mean() / hp[1].mean()
        offset = wp[2].mean() - hp[2].mean()
        print(f"plane_energy_cv_helios: {hp[1].std() / hp[1].mean():.4f}")
        print(f"plane_energy_cv_waveforest: {wp[1].std() / wp[1].mean():.4f}")
        rho_pi = 0.5 * math.cos(math.radians(a.tilt)) / math.pi
        print(f"plane_waveforest_energy_over_rho_cos_over_pi: {wp[1].mean() / rho_pi:.5f}")
        (hc, wc) = found["canopy"]
        print(f"canopy_apparent_reflectance_order1_waveforest: {math.pi * wc[1].mean():.4f}")
        print(f"canopy_energy_ratio: {wc[1].mean() / (scale * hc[1].mean()):.4f}")
        diff = wc[2].mean() - (hc[2].mean() + offset)
        print(f"canopy_centroid_diff_ns: {diff:.3f} ns")
        print(f"canopy_centroid_diff_cm: {100 * diff * C_M_PER_NS:.2f} cm")
        j = np.argmin(np.abs(hc[0][:, 1][None, :] - wc[0][:, 1][:, None]), axis=1)
        gap = np.abs(hc[0][j, 1] - wc[0][:, 1])
        per = wc[2] - (hc[2][j] + offset)
        print(f"canopy_matched_pulse_gap_m: {gap.max():.3f} m")
        print(f"canopy_centroid_rms_ns: {math.sqrt(np.mean(per ** 2)):.3f} ns")
        print(f"canopy_energy_ratio_matched_rms: {math.sqrt(np.mean((wc[1] / (scale * hc[1][j]) - 1) ** 2)):.4f}")
        # CPU per pulse: the marginal cost between the short and the long leg (scene loading and
        # BVH builds cancel); HELIOS's whole process, waveforest's tiles (trace + sensor twin)
        hs, ws = short["canopy"]
        h_cpu = 1000 * (hc[3] - hs[3]) / (len(hc[1]) - len(hs[1]))
        w1 = 1000 * (wc[3]["cpu_s"] - ws[3]["cpu_s"]) / (len(wc[1]) - len(ws[1]))
        w1_run = 1000 * (wc[3]["run_cpu_s"] - ws[3]["run_cpu_s"]) / (len(wc[1]) - len(ws[1]))
        cpu10 = []
        for length in (a.length, 3 * a.length):
            sub = tmp / "canopy" / f"{length:g}"
            _, e, _, r = run_waveforest(sub, tmp / "canopy" / "canopy.obj", rays, 10, length, a.rate)
            cpu10.append((r["cpu_s"], len(e)))
        w10 = 1000 * (cpu10[1][0] - cpu10[0][0]) / (cpu10[1][1] - cpu10[0][1])
        print(f"canopy_marginal_pulses_helios: {len(hc[1]) - len(hs[1])} pulses")
        print(f"canopy_marginal_pulses_waveforest: {len(wc[1]) - len(ws[1])} pulses")
        print(f"helios_cpu_ms_per_pulse: {h_cpu:.1f} ms")
        print(f"helios_cpu_s_short_leg: {hs[3]:.1f} s")
        print(f"waveforest_cpu_ms_per_pulse_order1: {w1:.1f} ms")
        print(f"waveforest_cpu_ms_per_pulse_order10: {w10:.1f} ms")
        print(f"waveforest_run_cpu_ms_per_pulse_order1: {w1_run:.1f} ms")
        print(f"speedup_order1: {h_cpu / w1:.1f} x")
        print(f"speedup_order1_whole_run: {h_cpu / w1_run:.1f} x")
        print(f"order10_over_helios: {w10 / h_cpu:.2f}")
        if a.baseline_src:
            legs = [(tmp / "canopy" / f"{length:g}", length) for length in (a.length, a.length, 3 * a.length)]
            base = baseline_marginal(a.baseline_src, legs, tmp / "canopy" / "canopy.obj", rays, a.rate)
            print(f"baseline_waveforest_cpu_ms_per_pulse_order1: {base:.1f} ms")
            print(f"speedup_order1_over_baseline: {base / w1:.2f} x")

if __name__ == "__main__":
    sys.exit(main())
