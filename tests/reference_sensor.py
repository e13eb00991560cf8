"""Slow, obviously correct NumPy references of the sensor kernels (tests only).

Each follows docs/method.md literally: the CFD really upsamples to the 0.05-ns grid, the
convolution is ``np.convolve``, the features walk the samples one by one.
"""

from __future__ import annotations

import math

import numpy as np

from waveforest.constants import RANGE_PER_NS

H = 0.05  # fine grid, ns


def cfd_reference(row, n, dt, mean, thr, frac, D, dead, max_echoes):
    """CFD echoes of one waveform on the literally upsampled 0.05-ns waveform.

    Returns (times_ns list, amplitudes list).
    """
    if n < 2:
        return [], []
    M = int(math.floor((n - 1) * dt / H + 1e-9)) + 1
    tf = np.arange(M) * H
    xf = np.interp(tf, np.arange(n) * dt, np.asarray(row[:n], dtype=np.float64) - mean)
    xd = np.zeros(M)
    if D < M:
        xd[D:] = xf[: M - D]
    y = frac * xf - xd
    Q = max(1, int(round(0.5 * D)))  # a crossing must last half a delay (CFD_PERSIST_FRACTION)
    times, amps = [], []
    m = m_lo = 0
    while len(times) < max_echoes and m < M:
        above = np.flatnonzero(xf[m:] > thr)
        if above.size == 0:
            break
        m_a = m + int(above[0])
        j = -1
        if y[m_a] <= 0:  # armed after the crossing: look back one dead time (at least a delay)
            lo = max(m_lo, m_a - max(dead, D))
            cand = np.flatnonzero(y[lo:m_a] > 0)
            if cand.size:
                k = lo + int(cand[-1])
                if not (y[k + 1: min(m_a + Q + 1, M)] > 0).any():
                    j = k
        if j < 0:
            mm = m_a + 1
            while mm < M:
                if y[mm - 1] > 0 and y[mm] <= 0:
                    pos = np.flatnonzero(y[mm: min(mm + Q, M)] > 0)
                    if pos.size == 0:
                        j = mm - 1
                        break
                    mm = mm + int(pos[0]) + 1
                    continue
                if xf[mm] <= thr:
                    break
                mm += 1
            if j < 0:
                m = mm + 1
                continue
        times.append((j + y[j] / (y[j] - y[j + 1])) * H)
        amps.append(xf[max(0, j - D): min(M - 1, j + 1 + dead) + 1].max())
        m_lo = j + 1 + dead
        m = m_lo
    return times, amps


def features_reference(row, n, dt, mean, sd, t_echo, seg_sd=3.0, rise_sd=2.0, search_ns=2.0):
    """First-echo features of one waveform: dict Npeaks, Apeak, FWHM, E, seg_start_ns, seg_end_ns."""
    nan = {"Npeaks": 0, "Apeak": np.nan, "FWHM": np.nan, "E": np.nan, "seg_start_ns": np.nan, "seg_end_ns": np.nan}
    v = np.asarray(row[:n], dtype=np.float64)
    if n < 1 or not np.isfinite(t_echo):
        return nan
    thr = mean + seg_sd * sd
    ke = min(max(int(math.floor(t_echo / dt + 0.5)), 0), n - 1)
    if not v[ke] > thr:
        reach = max(1, int(math.floor(search_ns / dt + 1e-9)))
        order = [k for d in range(1, reach + 1) for k in (ke - d, ke + d)]
        hits = [k for k in order if 0 <= k < n and v[k] > thr]
        if not hits:
            return nan
        ke = hits[0]
    a = ke
    while a > 0 and v[a - 1] > thr:
        a -= 1
    b = ke
    while b < n - 1 and v[b + 1] > thr:
        b += 1
    seg = v[a: b + 1]
    kp = a + int(np.argmax(seg))
    apeak = v[kp] - mean
    energy = float(np.sum(seg - mean) * dt)
    top = v[kp]
    if 0 < kp < n - 1 and v[kp - 1] - 2 * v[kp] + v[kp + 1] < 0:
        vl, vp, vr = v[kp - 1: kp + 2]  # vertex of the parabola through the peak sample and its neighbours
        top = vp + (vl - vr) ** 2 / (8 * (2 * vp - vl - vr))
    half = (mean + top) / 2
    left = [k for k in range(0, kp) if v[k] <= half]
    right = [k for k in range(kp, n) if v[k] <= half]
    fwhm = np.nan
    if left and right:
        kl, kr = left[-1], right[0]
        tl = np.interp(half, [v[kl], v[kl + 1]], [kl * dt, (kl + 1) * dt])
        tr = np.interp(half, [v[kr], v[kr - 1]], [kr * dt, (kr - 1) * dt])
        fwhm = tr - tl
    # peaks: a maximum counts if it rises > r above the minimum before it and falls > r below
    # it before the next counted rise (segment ends are minima at the threshold)
    r = rise_sd * sd
    ext = np.concatenate([[thr], seg, [thr]])
    peaks = 0
    lo = ext[0]
    hi = None
    for x in ext[1:]:
        if hi is None:
            lo = min(lo, x)
            if x > lo + r:
                hi = x
        else:
            hi = max(hi, x)
            if x < hi - r:
                peaks += 1
                hi = None
                lo = x
    return {"Npeaks": max(peaks, 1), "Apeak": apeak, "FWHM": fwhm, "E": energy,
            "seg_start_ns": a * dt, "seg_end_ns": b * dt}


def ar1_reference(z, phi):
    """AR(1) rows by the recursion, e[0] = z[0]."""
    z = np.asarray(z, dtype=np.float64)
    e = np.empty_like(z)
    for i in range(z.shape[0]):
        e[i, 0] = z[i, 0]
        for k in range(1, z.shape[1]):
            e[i, k] = phi * e[i, k - 1] + math.sqrt(1 - phi**2) * z[i, k]
    return e


def trigger_loss_reference(sigma, f):
    """Remove f of each row's total, bin by bin from the start."""
    out = np.array(sigma, dtype=np.float64)
    for i in range(out.shape[0]):
        left = f * out[i].sum()
        for j in range(out.shape[1]):
            take = min(left, out[i, j])
            out[i, j] -= take
            left -= take
    return out


def render_reference(sigma, t0_ns, range_m, t_s, s, noise_mean, noise_sd, dt, rng, *, record_ns=256.0,
                     pre_trigger_m=(3.3, 4.8), frac=0.5, D=72, dead=144, arming_sd=4.0, gain=None,
                     nonlinearity=0.0, noise_autocorr=0.0):
    """Eq. 7 pulse by pulse with np.convolve, np.interp and the CFD reference; unquantised.

    Same random draws as :func:`waveforest.sensor.render`. Returns (samples, first, trigger).
    """
    sigma = np.asarray(sigma, dtype=np.float64)
    n = sigma.shape[0]
    n_s = int(round(record_ns / dt))
    pre = rng.uniform(pre_trigger_m[0], pre_trigger_m[1], n) / RANGE_PER_NS
    phase = rng.random(n) * dt
    z = rng.standard_normal((n, n_s))
    e = ar1_reference(z, noise_autocorr) if noise_autocorr else z
    gain = np.ones(n) if gain is None else gain
    samples = np.zeros((n, n_s))
    first = np.full(n, np.nan)
    trig = np.full(n, np.nan)
    for i in range(n):
        v = np.convolve(sigma[i], s) * gain[i] / range_m[i] ** 2
        if nonlinearity:
            v = nonlinearity * np.tanh(v / nonlinearity)
        tv = t0_ns[i] + t_s[0] + 0.5 * H + H * np.arange(v.size)
        times, _ = cfd_reference(v, v.size, H, 0.0, arming_sd * noise_sd, frac, D, dead, 1)
        if times:
            trig[i] = tv[0] + times[0]
            start = trig[i] - pre[i]
            first[i] = phase[i] + math.ceil((start - phase[i]) / dt) * dt
            samples[i] = np.interp(first[i] + dt * np.arange(n_s), tv, v, left=0.0, right=0.0)
        samples[i] += noise_mean + noise_sd * e[i]
    return samples, first, trig


def nested_cv_reference(amplitudes, agc, groups, a, b):
    """Pooled within-target relative SD, target by target."""
    num, N, K = 0.0, 0, 0
    for g in sorted(set(groups.tolist())):
        m = groups == g
        A = amplitudes[m] / (1 + (agc[m] - a) * b)
        num += float(np.sum((A / A.mean() - 1) ** 2))
        N += int(m.sum())
        K += 1
    return math.sqrt(num / (N - K))


def make_pulse_table(samples, *, dataset="2010_12_1", source="real", sampling_ns=1.0, echo_time_ns=None,
                     echo_xy=None, anchor=None, direction=None, range_m=1000.0, agc=np.nan, intensity=None,
                     extra=None):
    """A pulse table (waveforest.io.pulses.PULSE_SCHEMA) around given waveforms, for tests.

    samples : (n, n_s) array (or list of 1-D arrays); echo_time_ns : (n,) first echo times (NaN: no
    echo); echo_xy : (n, 2) first-echo x, y; anchor, direction : (n, 3); extra : dict of columns.
    """
    import pyarrow as pa

    from waveforest.io.pulses import PULSE_SCHEMA

    rows = [np.asarray(r, dtype=np.float32) for r in samples]
    n = len(rows)
    full = lambda v: np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy()  # noqa: E731
    te = full(np.nan if echo_time_ns is None else echo_time_ns)
    anchor = np.zeros((n, 3)) if anchor is None else np.asarray(anchor, dtype=np.float64)
    direction = np.tile([0.0, 0.0, -1.0], (n, 1)) if direction is None else np.asarray(direction, dtype=np.float64)
    exy = np.zeros((n, 2)) if echo_xy is None else np.asarray(echo_xy, dtype=np.float64)
    has = np.isfinite(te)
    ez = anchor[:, 2] + direction[:, 2] * np.where(has, te, 0.0) * RANGE_PER_NS
    lst = lambda v: [[float(x)] if h else [] for x, h in zip(v, has)]  # noqa: E731
    inten = np.array([max(r) if len(r) else 0.0 for r in rows]) if intensity is None else full(intensity)
    cols = {
        "dataset": [dataset] * n, "pulse_id": np.arange(n, dtype=np.int64), "source": [source] * n,
        "gps_time": np.arange(n, dtype=np.float64),
        "sensor_x": anchor[:, 0] - direction[:, 0] * full(range_m), "sensor_y": anchor[:, 1] - direction[:, 1] * full(range_m),
        "sensor_z": anchor[:, 2] - direction[:, 2] * full(range_m),
        "dir_x": direction[:, 0], "dir_y": direction[:, 1], "dir_z": direction[:, 2],
        "anchor_x": anchor[:, 0], "anchor_y": anchor[:, 1], "anchor_z": anchor[:, 2],
        "range_m": full(range_m), "scan_angle_deg": np.zeros(n), "agc": full(agc),
        "sampling_ns": full(sampling_ns), "digitizer_gain": np.ones(n), "digitizer_offset": np.zeros(n),
        "samples": rows, "n_echoes": has.astype(np.int16),
        "echo_x": lst(exy[:, 0]), "echo_y": lst(exy[:, 1]), "echo_z": lst(ez),
        "echo_time_ns": lst(te), "echo_intensity": [[float(v)] if h else [] for v, h in zip(inten, has)],
    }
    table = pa.table({f.name: pa.array(cols[f.name], type=f.type) for f in PULSE_SCHEMA}, schema=PULSE_SCHEMA)
    for k, v in (extra or {}).items():
        table = table.append_column(k, pa.array(v))
    return table


TARGETS_2010 = [  # target_id, material, hdrf, calibration, agc, x, y, radius_m
    ("tarp14", "tarp", 0.14, 1, 1, 0.0, 0.0, 2.0),
    ("tarp21", "tarp", 0.21, 1, 1, 30.0, 0.0, 2.0),
    ("tarp41", "tarp", 0.41, 1, 1, 60.0, 0.0, 2.0),
    ("asphalt", "asphalt", 0.21, 1, 1, 0.0, 40.0, 3.0),
    ("sand", "sand", 0.34, 1, 1, 30.0, 40.0, 3.0),
    ("grass", "grass", 0.45, 0, 1, 60.0, 40.0, 3.0),
]


def write_campaign_tables(folder, dataset="2010_12_1", year=2010, targets=TARGETS_2010):
    """datasets.csv and targets.csv of a one-dataset campaign; returns their paths."""
    import pandas as pd

    folder.mkdir(parents=True, exist_ok=True)
    pd.DataFrame([{"dataset": dataset, "year": year, "mean_range_m": 1200, "pulse_width_fwhm_ns": 7.2,
                   "footprint_diameter_m": 0.18, "sampling_ns": 1.0}]).to_csv(folder / "datasets.csv", index=False)
    rows = [{"target_id": t[0], "year": year, "material": t[1], "hdrf": t[2], "calibration": t[3], "agc": t[4],
             "x": t[5], "y": t[6], "z": 100.0, "radius_m": t[7]} for t in targets]
    rows.append({"target_id": "roof_other_year", "year": year + 2, "material": "bitumen_roof", "hdrf": "",
                 "calibration": 0, "agc": 1, "x": 0.0, "y": 0.0, "z": 100.0, "radius_m": 3.0})
    pd.DataFrame(rows).to_csv(folder / "targets.csv", index=False)
    return folder / "datasets.csv", folder / "targets.csv"


def target_pulses(rng, system, *, per_target=80, b_true=0.012, agc_spread=20, noise_mean=10.0, noise_sd=1.5,
                  sampling_ns=1.0, n_other=40, dataset="2010_12_1", targets=TARGETS_2010, constant_agc=False,
                  sensor_effects=None):
    """A pulse table of planar-target pulses simulated through the signal model (Eq. 7), plus
    ``n_other`` pulses off the targets, with a known AGC law (gain = 1 + (AGC - a) b_true) and
    optionally the signal model's sensor effects (``render`` keywords).

    Returns (table, truth) with truth = dict(a, b, noise_mean, noise_sd, target_index (n,)).
    """
    from waveforest.sensor import render

    rows = []
    for k, t in enumerate(targets):
        r = np.sqrt(rng.uniform(0, (0.8 * t[7]) ** 2, per_target))
        phi = rng.uniform(0, 2 * np.pi, per_target)
        rows.append(np.column_stack([np.full(per_target, k), t[5] + r * np.cos(phi), t[6] + r * np.sin(phi),
                                     np.full(per_target, t[2])]))
    other = np.column_stack([np.full(n_other, -1), rng.uniform(100, 200, n_other), rng.uniform(100, 200, n_other),
                             np.full(n_other, 0.3)])
    p = np.concatenate(rows + [other])
    n = len(p)
    tidx = p[:, 0].astype(int)
    rho = p[:, 3]
    # the sensor's AGC: higher for darker targets (it drives the amplitude to a set point) plus jitter
    agc = np.round(100 + 60 * (0.3 - rho) + rng.integers(-agc_spread, agc_spread + 1, n)).astype(float)
    if constant_agc:
        agc[:] = np.round(agc.mean())
    a = agc.mean()
    gain = 1 + (agc - a) * b_true
    rng_m = rng.normal(1200.0, 18.0, n)
    zen = np.radians(rng.uniform(0, 15, n))
    az = rng.uniform(0, 2 * np.pi, n)
    d = np.column_stack([np.sin(zen) * np.cos(az), np.sin(zen) * np.sin(az), -np.cos(zen)])
    sig = np.zeros((n, 200))
    sig[:, 100] = rho / np.pi
    t0 = rng_m / RANGE_PER_NS - 100.5 * H  # the spike's bin centre is at the pulse's range
    rend = render(sig, t0, rng_m, system, noise_mean, noise_sd, sampling_ns, rng, gain=gain, **(sensor_effects or {}))
    te = rend.trigger_ns - rend.first_sample_ns
    target_xyz = np.column_stack([p[:, 1], p[:, 2], np.full(n, 100.0)])
    anchor = target_xyz - d * te[:, None] * RANGE_PER_NS
    table = make_pulse_table(rend.samples, dataset=dataset, sampling_ns=sampling_ns, echo_time_ns=te,
                             echo_xy=p[:, 1:3], anchor=anchor, direction=d, range_m=rng_m, agc=agc,
                             intensity=rend.samples.max(axis=1) - noise_mean)
    return table, {"a": a, "b": b_true, "noise_mean": noise_mean, "noise_sd": noise_sd, "target_index": tidx,
                   "gain": gain}
