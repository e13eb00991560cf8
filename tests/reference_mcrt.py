"""Slow, obviously correct reference of the MCRT tracer (docs/method.md §(d)), one ray at a time.

Pure Python/NumPy in float64 scene coordinates (no internal frame, no float32, no
wavefront batching, no Numba): each ray is followed order by order with a brute-force
Moller-Trumbore search over all triangles. The random numbers are the same counter-based
SplitMix64 stream as the kernels (written here with Python integers), so the two
implementations must give the same sigma up to rounding.
"""

from __future__ import annotations

import math

import numpy as np

C = 299_792_458.0 * 1e-9  # m/ns
MASK = (1 << 64) - 1
GOLDEN = 0x9E3779B97F4A7C15
EPS = 1e-4  # ray offset, m (constants.RAY_EPS_M)
MARGIN = 0.05  # start plane before the box, m (tracer.START_MARGIN_M)
LEAD = 1.0  # ns (tracer.T0_LEAD_NS)
PHONG = 40.0  # effects.SPECULAR_PHONG_EXPONENT


def mix(z: int) -> int:
    z &= MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    return z ^ (z >> 31)


def uniform(stream: int, order: int, slot: int) -> float:
    h = mix(stream + (order * 8 + slot + 1) * GOLDEN)
    return (h >> 11) * 2.0**-53


def master_key(seed: int) -> int:
    return int(np.random.SeedSequence(seed).generate_state(1, dtype=np.uint64)[0])


def frame_about(w, cos_t, sin_t, phi):
    """Duff et al. (2017) orthonormal basis about unit w; the vector at (theta, phi)."""
    wx, wy, wz = w
    sign = 1.0 if wz >= 0 else -1.0
    a = -1.0 / (sign + wz)
    b = wx * wy * a
    t1 = np.array([1.0 + sign * wx * wx * a, sign * b, -sign * wx])
    t2 = np.array([b, sign + wy * wy * a, -wy])
    return sin_t * (math.cos(phi) * t1 + math.sin(phi) * t2) + cos_t * np.asarray(w)


def nearest_hit(tri, o, d):
    """Brute force over all triangles (Moller-Trumbore): (t, index) of the nearest hit, or (inf, -1)."""
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    det = np.where(ok, det, 1.0)
    s = o - v0
    u = np.einsum("ij,ij->i", s, p) / det
    q = np.cross(s, e1)
    v = (q @ d) / det
    t = np.einsum("ij,ij->i", e2, q) / det
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    if not hit.any():
        return math.inf, -1
    t = np.where(hit, t, np.inf)
    j = int(np.argmin(t))
    return float(t[j]), j


def reference_trace(scene, origin, direction, footprint_m, range_m, n_rays, max_order, bin_ns,
                    viewed_diameter_m, seed, specular=0.0, hotspot=1.0, window_ns=100.0):
    """sigma, order totals, dropped sigma, first-hit counts and t0 of each beam.

    ``range_m`` NaN = collimated beam, else diverging with ``footprint_m`` at ``range_m``.
    """
    tri = scene.triangles.astype(np.float64)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    rho, tau, kind = scene.rho.astype(float), scene.tau.astype(float), scene.kind.astype(int)
    lo, hi = tri.reshape(-1, 3).min(0), tri.reshape(-1, 3).max(0)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    n_bins = int(math.ceil(window_ns / bin_ns - 1e-9))
    nb = len(origin)
    sigma = np.zeros((nb, n_bins))
    totals = np.zeros((nb, max_order))
    dropped = np.zeros(nb)
    first = np.zeros((nb, 5), int)
    t0s = np.zeros(nb)
    key = master_key(seed)
    r2 = (viewed_diameter_m / 2) ** 2
    for b in range(nb):
        S = np.asarray(origin[b], float)
        A = np.asarray(direction[b], float)
        plane = max(min((c - S) @ A for c in corners) - MARGIN, 0.0)
        t0 = 2 * plane / C - LEAD
        t0s[b] = t0
        helper = np.array([0.0, 0, 1]) if abs(A[2]) < 0.9 else np.array([1.0, 0, 0])
        e1 = np.cross(A, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(A, e1)
        sd = footprint_m[b] / (2 * math.sqrt(2))
        bkey = mix(key + b * GOLDEN)

        def add(order, value, total_path, b=b, t0=t0):
            totals[b, order - 1] += value
            k = math.floor((total_path / C - t0) / bin_ns)
            if 0 <= k < n_bins:
                sigma[b, k] += value
            else:
                dropped[b] += value

        for i in range(n_rays):
            stream = mix(bkey + i * GOLDEN)
            u1, u2 = uniform(stream, 0, 0), uniform(stream, 0, 1)
            rad = math.sqrt(-2 * math.log(1 - u1)) * sd
            off = rad * math.cos(2 * math.pi * u2) * e1 + rad * math.sin(2 * math.pi * u2) * e2
            if np.isfinite(range_m[b]):
                d = range_m[b] * A + off
                d /= np.linalg.norm(d)
                s = plane / (d @ A)
                o = S + s * d
            else:
                d, s, o = A.copy(), plane, S + off + plane * A
            power, path = 1.0 / n_rays, s
            for order in range(1, max_order + 1):
                t, j = nearest_hit(tri, o, d)
                if order == 1:
                    first[b, kind[j] if j >= 0 else 4] += 1
                if j < 0:
                    break
                x = o + t * d
                n = nrm[j]
                lit = n if d @ n <= 0 else -n
                path += t
                mirror = d - 2 * (d @ n) * n
                spec = specular if kind[j] == 1 else 0.0
                # receiver contribution
                v = S - x
                along = -(v @ A)
                perp = -v - along * A
                if perp @ perp <= r2:
                    dist = np.linalg.norm(v)
                    w = v / dist
                    cr = w @ lit
                    if order == 1:
                        cr = abs(cr)
                    if cr >= 0:
                        lobe = max(w @ mirror, 0.0) ** PHONG
                        brdf = (1 - spec) * rho[j] / math.pi + spec * rho[j] * (PHONG + 2) / (2 * math.pi) * lobe
                        coef, side = brdf * cr, lit
                    else:
                        coef, side = tau[j] / math.pi * (-cr), -lit
                    if order == 1 and kind[j] != 0:
                        coef *= hotspot
                    value = power * coef
                    if value > 0:
                        if order == 1:
                            add(1, value, 2 * path)
                        elif nearest_hit(tri, x + EPS * side, w)[0] > dist:
                            add(order, value, path + dist)
                if order == max_order or rho[j] + tau[j] <= 0:
                    break
                weight = rho[j] + tau[j]
                if uniform(stream, order, 0) * (rho[j] + tau[j]) < rho[j]:
                    out = lit
                    if spec > 0 and uniform(stream, order, 1) < spec:
                        ca = uniform(stream, order, 2) ** (1 / (PHONG + 1))
                        new = frame_about(mirror, ca, math.sqrt(max(0.0, 1 - ca * ca)),
                                          2 * math.pi * uniform(stream, order, 3))
                        cos_o = new @ lit
                        if cos_o <= 0:
                            break
                        weight *= (PHONG + 2) / (PHONG + 1) * cos_o
                    else:
                        u = uniform(stream, order, 2)
                        new = frame_about(out, math.sqrt(1 - u), math.sqrt(u), 2 * math.pi * uniform(stream, order, 3))
                else:
                    out = -lit
                    u = uniform(stream, order, 2)
                    new = frame_about(out, math.sqrt(1 - u), math.sqrt(u), 2 * math.pi * uniform(stream, order, 3))
                o = x + EPS * out
                d = new
                power *= weight
    return {"sigma": sigma, "order_totals": totals, "dropped": dropped, "first_hit_counts": first, "t0_ns": t0s}


# --------------------------------------------------------------------------- Sobol' sampler


def reverse32(x: int) -> int:
    return int(f"{x & 0xFFFFFFFF:032b}"[::-1], 2)


def owen32(x: int, seed: int) -> int:
    """Hash-based nested uniform scramble (Burley 2020, Vegdahl 2021 hash) + digital shift."""
    m = 0xFFFFFFFF
    x = reverse32(x)
    s = seed & m
    x = (x ^ (x * 0x3D20ADEA)) & m
    x = (x + s) & m
    x = (x * ((s >> 16) | 1)) & m
    x = (x ^ (x * 0x05526C56)) & m
    x = (x ^ (x * 0x53A22864)) & m
    return reverse32(x) ^ (seed >> 32)


def sobol_uniform(beam_key: int, ray: int, dim: int) -> float:
    """Coordinate ``dim`` of point ``ray`` of a beam's scrambled Sobol' set: the unscrambled
    point from scipy (Gray-code order, so point ``ray`` in natural order is scipy's point
    ``inverse_gray(ray)``), then the scramble seeded by the beam key and the dimension."""
    from scipy.stats import qmc

    g, inv = ray, 0
    while g:  # inverse Gray code
        inv ^= g
        g >>= 1
    eng = qmc.Sobol(dim + 1, scramble=False, bits=32)
    if inv:
        eng.fast_forward(inv)
    x = int(round(eng.random(1)[0, dim] * 2.0**32))
    seed = mix(beam_key ^ (((dim + 1) * 0x94D049BB133111EB) & MASK))
    return (owen32(x, seed) + 0.5) * 2.0**-32
