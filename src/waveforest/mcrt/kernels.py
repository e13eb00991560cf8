"""Numba kernels of the wavefront tracer (METHOD.md d): ray emission, one scattering order,
and the binning of receiver contributions.

Each private ``_..._kernel`` is a pure ``@njit`` function on contiguous arrays; the public
wrapper beside it checks shapes, dtypes and values. Geometry is in the internal frame of a
:class:`~waveforest.mcrt.prepare.PreparedScene` (scene coordinates minus its ``shift``).

Random numbers come from a counter-based generator: the ``k``-th uniform of ray ``i`` of
beam ``b`` at scattering order ``n`` is a SplitMix64 hash of (beam key, i, n, k), where the
beam key hashes the seed and the beam's index in the ``trace`` call. Results are therefore
identical whatever the number of threads, the chunking of beams or the order in which rays
are processed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from ..constants import C_M_PER_NS, KIND_GROUND, KIND_LEAF, RAY_EPS_M
from .threads import MIN_PARALLEL_RAYS, NumbaThreads

GOLDEN = np.uint64(0x9E3779B97F4A7C15)
"""SplitMix64 increment (2^64 / golden ratio)."""
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_TWO_M53 = 1.0 / 9007199254740992.0

DRAWS_PER_ORDER = 8
"""Uniforms reserved per ray and scattering order (counter stride)."""

SLOT_BRANCH, SLOT_LOBE, SLOT_DIR1, SLOT_DIR2 = 0, 1, 2, 3
"""Which uniform of a ray's order decides what: reflect/transmit, specular lobe, direction."""

MISS_KIND = 4
"""Code of a miss in ``first_hit_counts`` (after the element kinds 0..3)."""


# --------------------------------------------------------------------------- random numbers


@njit(cache=True, inline="always")
def _mix(z):
    """SplitMix64 finaliser of a uint64."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True, inline="always")
def _stream(beam_key, ray):
    """The random stream (a uint64) of one ray of a beam."""
    return _mix(beam_key + np.uint64(ray) * GOLDEN)


@njit(cache=True, inline="always")
def _uniform(stream, order, slot):
    """Uniform in [0, 1) number ``slot`` of scattering order ``order`` of a ray's stream."""
    c = np.uint64(order * DRAWS_PER_ORDER + slot + 1)
    return np.float64(_mix(stream + c * GOLDEN) >> _S11) * _TWO_M53


@njit(cache=True)
def _beam_keys_kernel(key, index, out):
    for j in range(index.size):
        out[j] = _mix(key + np.uint64(index[j]) * GOLDEN)


def beam_keys(key: int | np.uint64, index: np.ndarray) -> np.ndarray:
    """Per-beam stream keys from a master key and the beams' indices in the trace call.

    Parameters
    ----------
    key : uint64
        Master key (derived from the seed).
    index : (nb,) int64
        Index of each beam in the ``trace`` call.

    Returns
    -------
    (nb,) uint64
    """
    idx = np.ascontiguousarray(index, dtype=np.int64)
    if idx.ndim != 1 or np.any(idx < 0):
        raise ValueError("index: expected a 1-D array of non-negative beam indices")
    out = np.empty(idx.size, np.uint64)
    _beam_keys_kernel(np.uint64(key), idx, out)
    return out


# --------------------------------------------------------------------------- geometry helpers


@njit(cache=True, inline="always")
def _around(wx, wy, wz, cos_t, sin_t, phi):
    """Unit vector at polar angle (cos_t, sin_t) and azimuth ``phi`` about unit vector w.

    Orthonormal basis of Duff et al. (2017), branch-free except for the sign of w_z; the
    result is unit to rounding error.
    """
    sign = 1.0 if wz >= 0.0 else -1.0
    a = -1.0 / (sign + wz)
    b = wx * wy * a
    t1x, t1y, t1z = 1.0 + sign * wx * wx * a, sign * b, -sign * wx
    t2x, t2y, t2z = b, sign + wy * wy * a, -wy
    cp = math.cos(phi)  # sin from cos: one transcendental instead of two
    sp = math.sqrt(max(0.0, 1.0 - cp * cp))
    if phi > math.pi:
        sp = -sp
    x = sin_t * (cp * t1x + sp * t2x) + cos_t * wx
    y = sin_t * (cp * t1y + sp * t2y) + cos_t * wy
    z = sin_t * (cp * t1z + sp * t2z) + cos_t * wz
    return x, y, z


# --------------------------------------------------------------------------- data


@dataclass
class Rays:
    """Live rays of a wavefront (internal frame).

    Attributes
    ----------
    origin : (m, 3) float32, m
    direction : (m, 3) float32, unit
    power : (m,) float64
        Ray power, fraction of the pulse's emitted power.
    path_m : (m,) float64, m
        Path length from the sensor to ``origin`` (the part skipped outside the scene included).
    beam : (m,) int32
        Index of the ray's beam in the current chunk.
    ray : (m,) int32
        Index of the ray within its beam (its random-stream counter).
    """

    origin: np.ndarray
    direction: np.ndarray
    power: np.ndarray
    path_m: np.ndarray
    beam: np.ndarray
    ray: np.ndarray

    def __len__(self) -> int:
        return len(self.power)

    def take(self, index: np.ndarray) -> Rays:
        """The rays selected by an index array."""
        return Rays(self.origin[index], self.direction[index], self.power[index],
                    self.path_m[index], self.beam[index], self.ray[index])

    def head(self, m: int) -> Rays:
        """Views of the first ``m`` rays."""
        return Rays(self.origin[:m], self.direction[:m], self.power[:m], self.path_m[:m],
                    self.beam[:m], self.ray[:m])


@dataclass
class BeamFrame:
    """Per-beam constants of a chunk of beams in the internal frame.

    Attributes
    ----------
    sensor : (nb, 3) float64, m
        Sensor (= receiver) positions.
    axis : (nb, 3) float64
        Unit beam axes.
    t0_ns : (nb,) float64, ns
        Two-way time from emission of the left edge of sigma bin 0.
    key : (nb,) uint64
        Random-stream key of each beam (:func:`beam_keys`).
    """

    sensor: np.ndarray
    axis: np.ndarray
    t0_ns: np.ndarray
    key: np.ndarray

    def __len__(self) -> int:
        return len(self.key)


# --------------------------------------------------------------------------- emission


@njit(cache=True, parallel=True, nogil=True)
def _emit_kernel(sensor, axis, e1, e2, sd, range_m, plane_m, key, n_rays,
                 origin, direction, path, beam, ray):
    nb = sensor.shape[0]
    for j in prange(nb * n_rays):
        b = j // n_rays
        i = j - b * n_rays
        s = _stream(key[b], i)
        u1 = _uniform(s, 0, 0)
        u2 = _uniform(s, 0, 1)
        rad = math.sqrt(-2.0 * math.log(1.0 - u1)) * sd[b]  # Box-Muller, 1 - u1 in (0, 1]
        gx = rad * math.cos(2.0 * math.pi * u2)
        gy = rad * math.sin(2.0 * math.pi * u2)
        ax, ay, az = axis[b, 0], axis[b, 1], axis[b, 2]
        ox = gx * e1[b, 0] + gy * e2[b, 0]
        oy = gx * e1[b, 1] + gy * e2[b, 1]
        oz = gx * e1[b, 2] + gy * e2[b, 2]
        r = range_m[b]
        if r > 0.0:  # diverging: from the sensor point through the offset at range r
            dx, dy, dz = r * ax + ox, r * ay + oy, r * az + oz
            inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
            dx, dy, dz = dx * inv, dy * inv, dz * inv
            t = plane_m[b] / (dx * ax + dy * ay + dz * az)
            px = sensor[b, 0] + t * dx
            py = sensor[b, 1] + t * dy
            pz = sensor[b, 2] + t * dz
        else:  # collimated: parallel to the axis, offset at the sensor
            dx, dy, dz = ax, ay, az
            t = plane_m[b]
            px = sensor[b, 0] + ox + t * ax
            py = sensor[b, 1] + oy + t * ay
            pz = sensor[b, 2] + oz + t * az
        origin[j, 0], origin[j, 1], origin[j, 2] = px, py, pz
        direction[j, 0], direction[j, 1], direction[j, 2] = dx, dy, dz
        path[j] = t
        beam[j] = b
        ray[j] = i


def emit_rays(frame: BeamFrame, footprint_m, range_m, plane_m, n_rays: int) -> Rays:
    """The rays of a chunk of beams, started on a plane just before the scene (METHOD.md d).

    Ray offsets across the axis are Gaussian with per-axis SD ``footprint / (2 sqrt 2)``
    (irradiance exp(-(2r/d)^2), d the 1/e diameter). Each ray starts where it crosses the
    plane perpendicular to its beam's axis at distance ``plane_m`` from the sensor, and
    carries the skipped path length in float64.

    Parameters
    ----------
    frame : BeamFrame
    footprint_m : (nb,) float64, m
        1/e footprint diameters.
    range_m : (nb,) float64, m
        Range at which a diverging beam has its footprint; NaN or <= 0 = collimated.
    plane_m : (nb,) float64, m
        Distance of the start plane from the sensor along the axis, >= 0.
    n_rays : int
        Rays per beam; each carries power 1 / n_rays.

    Returns
    -------
    Rays
        ``nb * n_rays`` rays, beam-major.
    """
    nb = len(frame)
    if n_rays < 1:
        raise ValueError(f"n_rays: expected >= 1, got {n_rays}")
    sensor = np.ascontiguousarray(frame.sensor, np.float64)
    axis = np.ascontiguousarray(frame.axis, np.float64)
    if sensor.shape != (nb, 3) or axis.shape != (nb, 3):
        raise ValueError("frame: sensor and axis must be (nb, 3)")
    fp = np.ascontiguousarray(np.broadcast_to(np.asarray(footprint_m, np.float64), (nb,)))
    rng = np.nan_to_num(np.broadcast_to(np.asarray(range_m, np.float64), (nb,)), nan=0.0)
    plane = np.ascontiguousarray(np.broadcast_to(np.asarray(plane_m, np.float64), (nb,)))
    if np.any(fp < 0) or np.any(plane < 0):
        raise ValueError("footprint_m and plane_m must be >= 0")
    if not np.allclose(np.linalg.norm(axis, axis=1), 1.0, atol=1e-9):
        raise ValueError("frame.axis: expected unit vectors")
    # an orthonormal pair across each axis
    helper = np.where(np.abs(axis[:, [2]]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(axis, e1)
    m = nb * int(n_rays)
    origin = np.empty((m, 3), np.float32)
    direction = np.empty((m, 3), np.float32)
    path = np.empty(m, np.float64)
    beam = np.empty(m, np.int32)
    ray = np.empty(m, np.int32)
    _emit_kernel(sensor, axis, np.ascontiguousarray(e1), np.ascontiguousarray(e2),
                 fp / (2.0 * math.sqrt(2.0)), np.ascontiguousarray(rng), plane,
                 np.ascontiguousarray(frame.key, np.uint64), int(n_rays),
                 origin, direction, path, beam, ray)
    power = np.full(m, 1.0 / n_rays)
    return Rays(origin, direction, power, path, beam, ray)


# --------------------------------------------------------------------------- one order


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _scatter_kernel(order, last, org, dirs, power, path, beam, ray, tfar, prim, tri,
                    sensor, axis, t0_ns, key,
                    n_bins, bin_ns, radius2, specular, phong_n, hotspot, eps,
                    c_val, c_bin, sh_org, sh_dir, sh_t,
                    n_org, n_dir, n_power, n_path, alive):
    m = org.shape[0]
    inv_pi = 1.0 / math.pi
    lobe_norm = (phong_n + 2.0) / (2.0 * math.pi)
    lobe_weight = (phong_n + 2.0) / (phong_n + 1.0)
    inv_c = 1.0 / C_M_PER_NS
    inv_bin = 1.0 / bin_ns
    for i in prange(m):
        c_val[i] = 0.0
        c_bin[i] = -1
        sh_t[i] = 0.0
        alive[i] = False
        p = prim[i]
        if p < 0:
            continue  # escaped
        b = beam[i]
        nx, ny, nz = tri[p, 0], tri[p, 1], tri[p, 2]
        if nx == 0.0 and ny == 0.0 and nz == 0.0:
            continue  # degenerate triangle: absorb
        t = np.float64(tfar[i])
        dx, dy, dz = np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2])
        x = np.float64(org[i, 0]) + t * dx
        y = np.float64(org[i, 1]) + t * dy
        z = np.float64(org[i, 2]) + t * dz
        cos_in = dx * nx + dy * ny + dz * nz
        if cos_in > 0.0:  # s = normal on the illuminated side
            sx, sy, sz = -nx, -ny, -nz
        else:
            sx, sy, sz = nx, ny, nz
        r = tri[p, 3]
        tr = tri[p, 4]
        k = np.int64(tri[p, 5])
        length = path[i] + t
        # mirror direction of the incoming ray (specular lobe)
        mx = dx - 2.0 * cos_in * nx
        my = dy - 2.0 * cos_in * ny
        mz = dz - 2.0 * cos_in * nz
        spec = specular if k == KIND_LEAF else 0.0

        # ---- receiver contribution (Eq. 2), only inside the viewed cylinder
        vx, vy, vz = sensor[b, 0] - x, sensor[b, 1] - y, sensor[b, 2] - z
        along = -(vx * axis[b, 0] + vy * axis[b, 1] + vz * axis[b, 2])
        px, py, pz = -vx - along * axis[b, 0], -vy - along * axis[b, 1], -vz - along * axis[b, 2]
        if px * px + py * py + pz * pz <= radius2:
            dist = math.sqrt(vx * vx + vy * vy + vz * vz)
            wx, wy, wz = vx / dist, vy / dist, vz / dist
            cr = wx * sx + wy * sy + wz * sz
            side = 1.0
            if order == 1:  # monostatic: the path back is the path in, always the lit side
                cr = abs(cr)
                total = 2.0 * length
            else:
                total = length + dist
            if cr >= 0.0:
                brdf = r * inv_pi
                if spec > 0.0:
                    ca = wx * mx + wy * my + wz * mz
                    lobe = ca ** phong_n if ca > 0.0 else 0.0
                    brdf = (1.0 - spec) * r * inv_pi + spec * r * lobe_norm * lobe
                coef = brdf * cr
            else:  # receiver on the far side: diffuse transmission
                coef = tr * inv_pi * (-cr)
                side = -1.0
            if order == 1 and k != KIND_GROUND:
                coef *= hotspot
            val = power[i] * coef
            if val > 0.0:
                c_val[i] = val
                tb = (total * inv_c - t0_ns[b]) * inv_bin
                if tb >= 0.0 and tb < n_bins:
                    c_bin[i] = np.int64(tb)
                if order > 1:  # visibility ray towards the receiver
                    sh_org[i, 0] = x + side * eps * sx
                    sh_org[i, 1] = y + side * eps * sy
                    sh_org[i, 2] = z + side * eps * sz
                    sh_dir[i, 0], sh_dir[i, 1], sh_dir[i, 2] = wx, wy, wz
                    sh_t[i] = dist

        # ---- next order: reflect with probability rho / (rho + tau), else transmit
        if last or r + tr <= 0.0:
            continue
        s = _stream(key[b], ray[i])
        weight = r + tr
        if _uniform(s, order, SLOT_BRANCH) * (r + tr) < r:
            ox, oy, oz = sx, sy, sz
            if spec > 0.0 and _uniform(s, order, SLOT_LOBE) < spec:
                # Phong lobe about the mirror direction, pdf (n+1)/(2 pi) cos^n(alpha)
                ca = _uniform(s, order, SLOT_DIR1) ** (1.0 / (phong_n + 1.0))
                sa = math.sqrt(max(0.0, 1.0 - ca * ca))
                phi = 2.0 * math.pi * _uniform(s, order, SLOT_DIR2)
                ex, ey, ez = _around(mx, my, mz, ca, sa, phi)
                cos_o = ex * sx + ey * sy + ez * sz
                if cos_o <= 0.0:
                    continue  # below the surface: the lobe's energy loss at oblique incidence
                weight *= lobe_weight * cos_o
            else:
                u = _uniform(s, order, SLOT_DIR1)
                phi = 2.0 * math.pi * _uniform(s, order, SLOT_DIR2)
                ex, ey, ez = _around(ox, oy, oz, math.sqrt(1.0 - u), math.sqrt(u), phi)
        else:
            ox, oy, oz = -sx, -sy, -sz
            u = _uniform(s, order, SLOT_DIR1)
            phi = 2.0 * math.pi * _uniform(s, order, SLOT_DIR2)
            ex, ey, ez = _around(ox, oy, oz, math.sqrt(1.0 - u), math.sqrt(u), phi)
        n_org[i, 0] = x + eps * ox
        n_org[i, 1] = y + eps * oy
        n_org[i, 2] = z + eps * oz
        n_dir[i, 0], n_dir[i, 1], n_dir[i, 2] = ex, ey, ez
        n_power[i] = power[i] * weight
        n_path[i] = length
        alive[i] = True


@dataclass
class Scattered:
    """Result of one scattering order for every input ray (also reusable output buffers).

    Attributes
    ----------
    value : (m,) float64
        Receiver contribution (fraction of emitted power per sr); 0 = none.
    bin : (m,) int64
        sigma bin of the contribution; -1 = outside the window (counted as dropped).
    shadow_origin, shadow_direction : (m, 3) float32
        Visibility ray towards the receiver (orders >= 2, where ``value > 0``).
    shadow_tmax : (m,) float32, m
        Its length (distance to the receiver).
    origin, direction : (m, 3) float32
        Scattered rays of the next order (valid where ``alive``).
    power, path_m : (m,) float64
    alive : (m,) bool
    """

    value: np.ndarray
    bin: np.ndarray
    shadow_origin: np.ndarray
    shadow_direction: np.ndarray
    shadow_tmax: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    power: np.ndarray
    path_m: np.ndarray
    alive: np.ndarray

    @classmethod
    def empty(cls, m: int) -> Scattered:
        """Buffers for ``m`` rays."""
        return cls(np.empty(m), np.empty(m, np.int64), np.empty((m, 3), np.float32),
                   np.empty((m, 3), np.float32), np.empty(m, np.float32),
                   np.empty((m, 3), np.float32), np.empty((m, 3), np.float32),
                   np.empty(m), np.empty(m), np.empty(m, np.bool_))

    def __len__(self) -> int:
        return len(self.value)

    def head(self, m: int) -> Scattered:
        """Views of the first ``m`` entries."""
        return Scattered(*(getattr(self, f)[:m] for f in self.__dataclass_fields__))


def scatter(order: int, last: bool, rays: Rays, tfar: np.ndarray, prim: np.ndarray, prepared,
            frame: BeamFrame, n_bins: int, bin_ns: float, viewed_diameter_m: float,
            specular: float = 0.0, phong_n: float = 40.0, hotspot: float = 1.0,
            eps: float = RAY_EPS_M, out: Scattered | None = None) -> Scattered:
    """One scattering order of a wavefront: contributions, binning and new rays (METHOD.md d).

    For each ray that hit triangle ``prim`` at distance ``tfar``:

    * receiver contribution (Eq. 2) ``BRDF * cos(theta) * P`` with theta between the
      element normal and the direction to the receiver, BRDF = rho / pi on the lit side and
      tau / pi on the far side (orders >= 2; order 1 is always the lit side in a monostatic
      system), times ``hotspot`` for order-1 vegetation (kind != 0). Leaves (kind 1) with
      ``specular = s > 0`` reflect with BRDF (1 - s) rho / pi + s rho (n + 2) / (2 pi)
      cos^n(alpha), alpha between the receiver direction and the mirror direction;
      counted only if the hit lies within ``viewed_diameter_m / 2`` of the beam axis
      (perpendicular distance); binned by total path sensor -> hits -> receiver (order 1:
      twice the path in);
    * next ray: reflect with probability rho / (rho + tau) (cosine-weighted on the lit
      side; for specular leaves the Phong lobe with probability s, weight
      (n + 2) / (n + 1) cos(theta_out)), else transmit (cosine-weighted on the far side);
      power times (rho + tau); origin offset by ``eps`` along the normal on the outgoing
      side. No new rays when ``last``.

    Parameters
    ----------
    order : int
        Scattering order of these hits, >= 1.
    last : bool
        True at the highest order (no new rays).
    rays : Rays
    tfar : (m,) float32, m
    prim : (m,) int32
        Triangle hit, -1 = miss.
    prepared : PreparedScene
    frame : BeamFrame
    n_bins : int
    bin_ns, viewed_diameter_m, specular, phong_n, hotspot, eps : float
    out : Scattered, optional
        Buffers of at least ``m`` rays to write into (avoids allocation per order).

    Returns
    -------
    Scattered
        ``m`` entries (views of ``out`` if given).
    """
    m = len(rays)
    if order < 1:
        raise ValueError(f"order: expected >= 1, got {order}")
    if tfar.shape != (m,) or prim.shape != (m,) or tfar.dtype != np.float32 or prim.dtype != np.int32:
        raise ValueError(f"tfar, prim: expected float32 and int32 of shape ({m},)")
    if rays.origin.dtype != np.float32 or rays.direction.dtype != np.float32:
        raise ValueError("rays: origin and direction must be float32")
    if n_bins < 1 or bin_ns <= 0 or viewed_diameter_m <= 0:
        raise ValueError("n_bins, bin_ns and viewed_diameter_m must be positive")
    if not 0.0 <= specular <= 1.0 or hotspot < 0 or phong_n < 0:
        raise ValueError("specular must be in [0, 1], hotspot and phong_n >= 0")
    tri = prepared.tri_data
    if tri.ndim != 2 or tri.shape[1] < 6 or not tri.flags.c_contiguous:
        raise ValueError("prepared.tri_data: expected a C-contiguous (n, >= 6) float64 array")
    if m and prim.max() >= len(tri):
        raise ValueError(f"prim: index {prim.max()} out of range for {len(tri)} triangles")
    if m and (rays.beam.min() < 0 or rays.beam.max() >= len(frame)):
        raise ValueError("rays.beam: index out of range of the beam frame")
    if out is None:
        out = Scattered.empty(m)
    elif len(out) < m:
        raise ValueError(f"out: buffers for {len(out)} rays, need {m}")
    o = out.head(m)
    with NumbaThreads(1 if m < MIN_PARALLEL_RAYS else None):
        _scatter(order, last, rays, tfar, prim, tri, frame, n_bins, bin_ns, viewed_diameter_m, specular,
                 phong_n, hotspot, eps, o)
    return o


def _scatter(order, last, rays, tfar, prim, tri, frame, n_bins, bin_ns, viewed_diameter_m, specular,
             phong_n, hotspot, eps, o):
    """Call :func:`_scatter_kernel` on validated inputs (``o``: the output views)."""
    _scatter_kernel(int(order), bool(last), rays.origin, rays.direction, rays.power, rays.path_m,
                    rays.beam, rays.ray, tfar, prim, tri,
                    frame.sensor, frame.axis, frame.t0_ns, frame.key,
                    int(n_bins), float(bin_ns), (0.5 * viewed_diameter_m) ** 2,
                    float(specular), float(phong_n), float(hotspot), float(eps),
                    o.value, o.bin, o.shadow_origin, o.shadow_direction, o.shadow_tmax,
                    o.origin, o.direction, o.power, o.path_m, o.alive)


@njit(cache=True, nogil=True)
def _compact_kernel(alive, org, dirs, power, path, beam, ray,
                    d_org, d_dir, d_power, d_path, d_beam, d_ray):
    k = 0
    for i in range(alive.size):
        if alive[i]:
            d_org[k, 0], d_org[k, 1], d_org[k, 2] = org[i, 0], org[i, 1], org[i, 2]
            d_dir[k, 0], d_dir[k, 1], d_dir[k, 2] = dirs[i, 0], dirs[i, 1], dirs[i, 2]
            d_power[k] = power[i]
            d_path[k] = path[i]
            d_beam[k] = beam[i]  # in place is safe: k <= i
            d_ray[k] = ray[i]
            k += 1
    return k


def compact(scattered: Scattered, rays: Rays, dest: Rays) -> Rays:
    """The next order's live rays, packed to the front of ``dest`` (order kept).

    Parameters
    ----------
    scattered : Scattered
        Output of :func:`scatter` for ``rays`` (new origins, directions, powers, paths).
    rays : Rays
        The rays that were scattered (their beam and ray indices are carried over).
    dest : Rays
        Buffers of at least ``len(rays)`` rays; may be the buffers ``rays`` views.

    Returns
    -------
    Rays
        Views of the first k entries of ``dest``.
    """
    m = len(rays)
    if len(scattered) != m or len(dest) < m:
        raise ValueError("compact: scattered must match rays, dest must hold them")
    k = _compact_kernel(scattered.alive, scattered.origin, scattered.direction, scattered.power,
                        scattered.path_m, rays.beam, rays.ray, dest.origin, dest.direction,
                        dest.power, dest.path_m, dest.beam, dest.ray)
    return dest.head(k)


# --------------------------------------------------------------------------- binning


@njit(cache=True, nogil=True)
def _accumulate_kernel(index, beam, value, bins, layer, order, acc, dropped, totals):
    for j in range(index.size):
        i = index[j]
        b = beam[i]
        v = value[i]
        totals[b, order - 1] += v
        k = bins[i]
        if k >= 0:
            acc[b, layer, k] += v
        else:
            dropped[b] += v


def accumulate(index: np.ndarray, beam: np.ndarray, value: np.ndarray, bins: np.ndarray,
               order: int, acc: np.ndarray, dropped: np.ndarray, totals: np.ndarray,
               by_order: bool) -> None:
    """Add the contributions ``index`` into sigma (serial, so no races), in place.

    Parameters
    ----------
    index : (k,) int64
        Rays whose contribution counts (visible from the receiver).
    beam : (m,) int32
    value : (m,) float64
    bins : (m,) int64
        sigma bin, -1 = outside the window (added to ``dropped``).
    order : int
    acc : (nb, n_layers, n_bins) float64
        sigma per beam (one layer, or one layer per order when ``by_order``).
    dropped : (nb,) float64
    totals : (nb, max_order) float64
    by_order : bool
    """
    idx = np.ascontiguousarray(index, np.int64)
    if acc.ndim != 3 or dropped.shape != acc.shape[:1] or totals.shape[0] != acc.shape[0]:
        raise ValueError("acc, dropped, totals: inconsistent shapes")
    if not 1 <= order <= totals.shape[1]:
        raise ValueError(f"order: expected 1..{totals.shape[1]}, got {order}")
    layer = order - 1 if by_order else 0
    if layer >= acc.shape[1]:
        raise ValueError("acc: too few layers for by_order")
    if idx.size and (idx.min() < 0 or idx.max() >= len(value)):
        raise ValueError("index: out of range")
    if np.any(bins[idx] >= acc.shape[2]):
        raise ValueError("bins: index beyond the sigma window")
    _accumulate_kernel(idx, beam, value, bins, layer, order, acc, dropped, totals)


@njit(cache=True, parallel=True, nogil=True)
def take_rays(org, dirs, index):
    """Rows ``index`` of a ray batch's origins and directions, as new contiguous arrays.

    The same as ``org[index], dirs[index]``, in a tenth of NumPy's time for (m, 3) float32
    rows (2 vs 19 ms for 240,000 rays on one core).
    """
    m = index.size
    o = np.empty((m, 3), org.dtype)
    d = np.empty((m, 3), dirs.dtype)
    for i in prange(m):
        j = index[i]
        o[i, 0], o[i, 1], o[i, 2] = org[j, 0], org[j, 1], org[j, 2]
        d[i, 0], d[i, 1], d[i, 2] = dirs[j, 0], dirs[j, 1], dirs[j, 2]
    return o, d
