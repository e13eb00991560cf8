"""A directed test: the gap's pooled terms projected on each candidate's signature.

Usage::

    python benchmarks/diagnose_directed.py limits RESULTS[:CONFIG] [--replicates 20] [--values 3] --out DIR
    python benchmarks/diagnose_directed.py campaigns --signatures DIR/signatures.parquet RESULTS[:CONFIG] ...

The omnibus test of ``diagnose`` squares every pooled term d_bar, l_bar (label x feature) and
averages them: an effect that moves a few terms is diluted by the rest. The directed test of a
candidate c with signature s (its pooled terms at the ladder's strongest value against the base
model, one independent seed, common random numbers) is the matched filter::

    T_c = sum_i w_i v_i,   w_i = s_i / sd_i^2,   z_c = T_c / robust_sd(T_c*)

v the data's pooled terms, sd_i their cluster-bootstrap SDs and T_c* the same projection of the
bootstrap replicates (the terms' correlations enter through them). z_c is calibrated on the
off replicates (divided by their RMS) and a data set is *detected* when the calibrated z of any
candidate exceeds ``--threshold`` (default 2.576: one-sided 0.05 over 10 candidates, Bonferroni).

``limits`` runs the diagnosis's power analysis design (its pool, seeds and replicates:
:mod:`waveforest.diagnose.power`) with every ladder value evaluated (``--values``, default 3: half
the test value's distance from off, the test value and the bound: :func:`.power.ladder`) and prints
per candidate the power at off and at each value of three tests: ``omnibus_fe`` (the diagnosis's:
the first echo's gap above its calibrated floor), ``directed_fe`` and ``directed_ww`` (the directed
test on the first echo's and on the whole waveform's terms); then each test's limit and that of
``combined`` (omnibus_fe or directed_ww): per replicate the strength above which it detects every
value tried (the margin interpolated between values, in strength squared for the gap, linearly for
z), the limit the ceil(power x replicates)-th smallest; ``limit_ratio_<test>_<effect>`` against
``omnibus_fe`` (distances from off: 0.5 = halved). Writes DIR/signatures.parquet and
DIR/replicates.csv (signatures are reused when present).

Each directed test is also printed as ``quasi_<set>``: z further divided by sqrt(phi / mean phi of
the off replicates) where that exceeds 1, phi the mean square of the standardised terms once the
candidate's signature is fitted out (an over-dispersion scale: a misfit in every other direction
weakens the candidate's evidence); ``combined_quasi`` is omnibus_fe or quasi_ww.

``campaigns`` applies the directed test to campaigns' own data (the diagnosis's base
simulation, seed and bootstrap) with signatures from ``limits`` and each campaign's own
calibration (its off replicates): on campaigns without effects, a z above the threshold is a
false alarm.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
from diagnose_floor import study_inputs

from waveforest.diagnose import catalogue as cat
from waveforest.diagnose.gap import ALL_FEATURES, FEATURES, GapData, cell_statistics, pooled, sample_universe
from waveforest.diagnose.power import _assemble, _calibrated, _Pool, _Replicate, floor_calibration, ladder
from waveforest.diagnose.replicate_cache import simulate_all
from waveforest.rng import named_seeds
from waveforest.stats.bootstrap import bootstrap_weights, robust_sd

SETS = {"fe": FEATURES, "ww": ALL_FEATURES}


def pooled_terms(real, sim, universe, weights, search, features):
    """The pooled terms d_bar, l_bar per label x feature (Series), and their bootstrap replicates
    ((B, K) DataFrame) when ``weights`` are given."""
    data = GapData.build(real, sim, universe, **{**search.gap_kw, "features": features, "floor_scale": 1.0})
    mask = data.valid
    keep = (data.label_members[:, :, None] & mask[None]).any(axis=1)
    labels = pd.factorize(data.cells["species"])[1]
    names = [f"{labels[i]}|{data.features[k]}" for i, k in zip(*np.nonzero(keep))]
    idx = [f"d|{n}" for n in names] + [f"l|{n}" for n in names]
    pt = cell_statistics(data)
    v = pd.Series(np.concatenate([pooled(data, pt["d"], mask), pooled(data, pt["log_sd_ratio"], mask)]), idx)
    if weights is None:
        return v
    bt = cell_statistics(data, weights)
    vb = np.concatenate([pooled(data, bt["d"], mask), pooled(data, bt["log_sd_ratio"], mask)], axis=-1)
    return v, pd.DataFrame(vb, columns=idx)


def directed_z(v: pd.Series, vb: np.ndarray, sd: np.ndarray, sig: pd.Series) -> tuple[float, float]:
    """(z, phi): z of the projection of ``v`` on ``sig`` (module docstring) and phi, the mean
    square of the standardised terms v / sd left once their least-squares multiple of the
    standardised signature is taken out (the misfit in every other direction); ``vb`` the
    bootstrap replicates of ``v`` with NaN as 0, ``sd`` their robust SDs."""
    s = sig.reindex(v.index).to_numpy()
    x = v.to_numpy()
    ok = np.isfinite(x) & np.isfinite(s) & np.isfinite(sd) & (sd > 0)
    w = np.where(ok, s / np.where(ok, sd, 1.0) ** 2, 0.0)
    y, st = x[ok] / sd[ok], s[ok] / sd[ok]
    resid = y - st * (y @ st) / (st @ st)
    return float(np.where(ok, x, 0.0) @ w) / float(robust_sd(vb @ w)), float(np.mean(resid ** 2))


def signatures(keys, simulate, search, candidates, seed, values) -> pd.DataFrame:
    """Pooled terms of each candidate at its ladder's strongest value against the base model."""
    s_sig = named_seeds("power", int(seed), 2, n=1)[0]  # a stream of its own
    universe = sample_universe(keys)
    off = simulate_all(simulate, keys, {}, s_sig, 1)
    rows = []
    for name in candidates:
        value = cat.from_u(name, ladder(name, values)[-1])
        on = simulate_all(simulate, keys, cat.with_effect({}, name, value), s_sig, 1)
        for fs, feats in SETS.items():
            sig = pooled_terms(on, off, universe, None, search, feats)
            rows += [{"effect": name, "value": value, "features": fs, "term": t, "s": x} for t, x in sig.items()]
        print(f"signature {name} {value:.4g}", file=sys.stderr, flush=True)
    return pd.DataFrame(rows)


def sig_table(sigs: pd.DataFrame) -> dict:
    """(effect, feature set) -> its signature's terms, from :func:`signatures`' table."""
    return {(e, fs): g.set_index("term")["s"] for (e, fs), g in sigs.groupby(["effect", "features"])}


def evaluate(real, sim, universe, weights, search, sigs: dict, candidates) -> dict:
    """Raw directed z of every candidate and feature set for one data set."""
    out = {}
    for fs, feats in SETS.items():
        v, vb = pooled_terms(real, sim, universe, weights, search, feats)
        sd, vb = robust_sd(vb.to_numpy()), np.nan_to_num(vb.to_numpy())  # once for all candidates
        for c in candidates:
            out[f"z_{fs}_{c}"], out[f"phi_{fs}_{c}"] = directed_z(v, vb, sd, sigs[(c, fs)])
    return out


def crossing(strengths: np.ndarray, margin: np.ndarray, power: float = 1.0) -> float:
    """Strength above which one replicate detects every value tried: the last sign change of
    ``margin`` (detected where > 0; strengths ascending, off first), linear in strength**power
    between the two values around it (0 when off is detected; inf when the strongest is not)."""
    miss = np.nonzero(~(margin > 0))[0]
    if miss.size == 0:
        return 0.0
    k = miss[-1]
    if k == len(margin) - 1:
        return math.inf
    a, b = strengths[k] ** power, strengths[k + 1] ** power
    return float((a + (b - a) * (-margin[k]) / (margin[k + 1] - margin[k])) ** (1.0 / power))


def run_limits(a) -> None:
    r, _, c = a.results.partition(":")
    settings, keys, _, simulate = study_inputs(Path(r), Path(c) if c else None)
    keys = keys.assign(sample_id=keys["sample_id"].astype(str))
    search = replace(settings.search, floor_scale=1.0, features=FEATURES)
    cands = list(a.candidates or search.candidates)
    power = replace(settings.power, replicates=a.replicates)
    universe = sample_universe(keys)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    sig_path = out / "signatures.parquet"
    if sig_path.exists():
        sigs_df = pd.read_parquet(sig_path)
    else:
        sigs_df = signatures(keys, simulate, search, cands, settings.seed, a.values)
        sigs_df.to_parquet(sig_path)
    sigs = sig_table(sigs_df)
    n_pool = min(power.pool, power.replicates + 1)
    pool = _Pool(keys, simulate, named_seeds("power", int(settings.seed), n=n_pool), search.replicates,
                 lambda s: print(s, file=sys.stderr, flush=True))
    reps = [_Replicate(pool, search, s, universe) for s in named_seeds("power", int(settings.seed), 1, n=power.replicates)]
    models = [("off", 0.0, {})]
    for name in cands:
        u0 = cat.off_u(name)
        models += [(name, abs(u - u0), cat.with_effect({}, name, cat.from_u(name, u))) for u in ladder(name, a.values)]
    rows = []
    for name, strength, eff in models:
        for i, rep in enumerate(reps):
            real = _assemble([pool.get(eff, k) for k in range(n_pool)], rep.real_pick, universe)
            g, f, lb = rep.test(eff)
            rows.append({"effect": name, "strength": strength, "rep": i, "gap": g, "floor": f, "lb": lb,
                         **evaluate(real, rep.sim, universe, rep.weights, search, sigs, cands)})
    t = pd.DataFrame(rows)
    t.to_csv(out / "replicates.csv", index=False)
    report(t, cands, power.power, a.threshold)


def calibrated(z, off: pd.DataFrame, fs: str, c: str, quasi: bool):
    """z of candidate ``c`` on feature set ``fs`` (a replicates table's column or one data set's
    value) over the RMS of the off replicates' z; with ``quasi`` also over sqrt(phi / mean phi
    of the off replicates) where that ratio exceeds 1 (the data's misfit in the other
    directions, an over-dispersion scale)."""
    x = z[f"z_{fs}_{c}"] / math.sqrt(np.mean(off[f"z_{fs}_{c}"] ** 2))
    if quasi:
        x = x / np.sqrt(np.maximum(1.0, z[f"phi_{fs}_{c}"] / np.mean(off[f"phi_{fs}_{c}"])))
    return x


TESTS = (("directed", False), ("quasi", True))
"""The directed test without and with the over-dispersion scale."""


def report(t: pd.DataFrame, cands, target: float, thr: float) -> None:
    off = t[t["effect"] == "off"]
    cal = floor_calibration(off[["gap", "floor", "lb"]].to_numpy())
    print(f"floor_scale_fe: {cal.scale:.3f} factor")
    lb = _calibrated(t[["gap", "floor", "lb"]].to_numpy(), cal.scale)[:, 2]
    margin = {"omnibus_fe": (lb, 2.0)}
    for fs in SETS:
        for c in cands:
            print(f"z_scale_{fs}_{c}: {math.sqrt(np.mean(off[f'z_{fs}_{c}'] ** 2)):.3f} rms of off z")
        for name, quasi in TESTS:
            zc = np.column_stack([calibrated(t, off, fs, c, quasi) for c in cands])
            margin[f"{name}_{fs}"] = (zc.max(axis=1) - thr, 1.0)
    for test, (m, _) in margin.items():
        print(f"false_alarms_{test}: {int((m[t['effect'] == 'off'] > 0).sum())} of {len(off)}")
    needed = max(1, math.ceil(target * len(off) - 1e-9))
    m_off = {test: m[(t["effect"] == "off").to_numpy()] for test, (m, _) in margin.items()}
    for c in cands:
        sel = (t["effect"] == c).to_numpy()
        s = np.r_[0.0, np.sort(t.loc[sel, "strength"].unique())]
        cross = {}
        for test, (m, pw_exp) in margin.items():
            mm = np.column_stack([m_off[test]] + [m[sel & (t["strength"] == x).to_numpy()] for x in s[1:]])
            cross[test] = np.array([crossing(s, row, pw_exp) for row in mm])
            print(f"power_{test}_{c}: " + " ".join(f"{p:.2f}" for p in (mm > 0).mean(axis=0)) + " at strengths "
                  + " ".join(f"{x:.3g}" for x in s))
        cross["combined"] = np.minimum(cross["omnibus_fe"], cross["directed_ww"])
        cross["combined_quasi"] = np.minimum(cross["omnibus_fe"], cross["quasi_ww"])
        u0 = cat.off_u(c)
        sign = math.copysign(1.0, ladder(c, 1)[-1] - u0)
        base = np.sort(cross["omnibus_fe"])[needed - 1]
        for test, x in cross.items():
            x = np.sort(x)[needed - 1]
            v = cat.from_u(c, u0 + sign * x) if math.isfinite(x) else math.nan
            print(f"limit_{test}_{c}: {v:.4g} {cat.UNITS[c]}")
            if test != "omnibus_fe":
                print(f"limit_ratio_{test}_{c}: {x / base:.3f} of omnibus_fe")


def run_campaigns(a) -> None:
    sigs = sig_table(pd.read_parquet(a.signatures))
    cands = sorted({e for e, _ in sigs})
    for arg in a.results:
        t0 = time.perf_counter()
        r, _, c = arg.partition(":")
        settings, keys, real, simulate = study_inputs(Path(r), Path(c) if c else None)
        keys = keys.assign(sample_id=keys["sample_id"].astype(str))
        real = real.assign(sample_id=real["sample_id"].astype(str))
        search = replace(settings.search, floor_scale=1.0, features=FEATURES)
        universe = sample_universe(keys)
        power = replace(settings.power, replicates=a.replicates)
        n_pool = min(power.pool, power.replicates + 1)
        pool = _Pool(keys, simulate, named_seeds("power", int(settings.seed), n=n_pool), search.replicates, None)
        reps = [_Replicate(pool, search, s, universe)
                for s in named_seeds("power", int(settings.seed), 1, n=power.replicates)]
        off = pd.DataFrame([evaluate(_assemble([pool.get({}, k) for k in range(n_pool)], rep.real_pick, universe),
                                     rep.sim, universe, rep.weights, search, sigs, cands) for rep in reps])
        _, s_after, s_boot = named_seeds("missing_effects", int(settings.seed), n=3)
        sim = simulate_all(simulate, keys, {}, int(s_after), search.replicates)
        w = bootstrap_weights(universe, search.n_boot, int(s_boot))
        z = evaluate(real, sim, universe, w, search, sigs, cands)
        for fs in SETS:
            for name, quasi in TESTS:
                zc = {c: float(calibrated(z, off, fs, c, quasi)) for c in cands}
                best = max(zc, key=zc.get)
                print(f"{r} {name}_{fs}: max z {zc[best]:.2f} ({best}); "
                      + " ".join(f"{c} {v:.2f}" for c, v in zc.items()) + f" [{time.perf_counter() - t0:.0f} s]",
                      flush=True)
                print(f"alarm_{name}_{fs}: {int(zc[best] > a.threshold)} {Path(r).parent.name}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="mode", required=True)
    lim = sub.add_parser("limits")
    lim.add_argument("results")
    lim.add_argument("--out", required=True)
    lim.add_argument("--values", type=int, default=3)
    lim.add_argument("--candidates", nargs="*", default=None)
    camp = sub.add_parser("campaigns")
    camp.add_argument("results", nargs="+")
    camp.add_argument("--signatures", required=True)
    for q in (lim, camp):
        q.add_argument("--replicates", type=int, default=20)
        q.add_argument("--threshold", type=float, default=2.576)
    a = p.parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    run_limits(a) if a.mode == "limits" else run_campaigns(a)
    print(f"wall_time: {time.perf_counter() - t0:.1f} s")
    print(f"cpu_time: {time.process_time() - c0:.1f} s")


if __name__ == "__main__":
    main()
