"""Simple scenes with known answers, for testing and benchmarking the tracer.

These are not vegetation models (see :mod:`waveforest.vegetation`): a plane, a
semi-transparent sheet over a ground, and a turbid layer of small random leaves (Poisson
positions, spherical leaf angle distribution), whose sigma, per-order totals and gap
fractions have analytic values.
"""

from __future__ import annotations

import numpy as np

from ..constants import KIND_GROUND, KIND_LEAF
from ..scene import Scene


def plane(size_m: float = 6.0, z: float = 0.0, rho: float = 0.3, tau: float = 0.0,
          kind: int = KIND_GROUND, tilt_deg: float = 0.0, tilt_azimuth_deg: float = 0.0,
          center=(0.0, 0.0)) -> Scene:
    """A square plane (two triangles) through (center, z), tilted by ``tilt_deg``.

    Parameters
    ----------
    size_m : float
        Side of the square before tilting (its horizontal projection shrinks by cos tilt
        along the tilt direction), m.
    tilt_deg : float
        Angle between the plane's normal and the vertical, degrees.
    tilt_azimuth_deg : float
        Compass azimuth (clockwise from +y) towards which the normal leans, degrees.

    Returns
    -------
    Scene
        Normal (right-hand rule) = (sin t sin a, sin t cos a, cos t).
    """
    h = 0.5 * size_m
    sq = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    t, a = np.radians(tilt_deg), np.radians(tilt_azimuth_deg)
    # rotate about the horizontal axis perpendicular to the tilt azimuth
    n = np.array([np.sin(t) * np.sin(a), np.sin(t) * np.cos(a), np.cos(t)])
    u = np.array([np.cos(a), -np.sin(a), 0.0])  # horizontal, perpendicular to the lean
    v = np.cross(n, u)
    verts = sq[:, [0]] * u + sq[:, [1]] * v + np.array([center[0], center[1], z])
    tri = np.stack([verts[[0, 1, 2]], verts[[0, 2, 3]]])
    # u x v = n: the vertex order above gives the normal n
    return Scene(tri.astype(np.float32), rho, tau, kind)


def sheet_over_ground(size_m: float = 40.0, height_m: float = 0.05, rho: float = 0.47,
                      tau: float = 0.5, ground_rho: float = 0.3) -> Scene:
    """A horizontal semi-transparent (rho, tau) leaf sheet ``height_m`` above a Lambertian ground.

    Nadir analytic per-order sigma (infinite layers, visibility rays blocked by the sheet):
    order 1 = rho / pi; even orders = 0; order 2k + 1 (k >= 1) =
    tau^2 ground_rho^k rho^(k - 1) / pi.
    """
    ground = plane(size_m, 0.0, ground_rho, 0.0, KIND_GROUND)
    sheet = plane(size_m, height_m, rho, tau, KIND_LEAF)
    return Scene.concat([ground, sheet])


def random_leaves(lai: float, z_range=(0.0, 1.2), size_m: float = 6.0, leaf_area_m2: float = 6.7e-4,
                  seed: int = 0, leaf_rho: float = 0.47, leaf_tau: float = 0.50,
                  ground_rho: float = 0.30, ground: bool = True) -> Scene:
    """A layer of small equilateral triangle "leaves": Poisson positions, spherical LAD.

    Leaf centres are uniform in ``[-size/2, size/2]^2 x z_range``; their number is Poisson
    with mean ``lai * size^2 / leaf_area``; normals are uniform on the sphere (spherical
    leaf angle distribution, G = 1/2 in every direction) with a uniform in-plane rotation.
    The expected gap fraction along a direction of zenith angle theta is
    exp(-0.5 lai / cos theta) away from the layer's sides.

    Parameters
    ----------
    lai : float
        One-sided leaf area index, m^2 m^-2.
    z_range : (2,) float
        Heights of the leaf centres, m.
    size_m : float
        Side of the square layer and of the ground, m.
    leaf_area_m2 : float
        One-sided area of a leaf, m^2 (6.7e-4 gives ~180,000 leaves at LAI 3.35 on 6 x 6 m).
    seed : int
    leaf_rho, leaf_tau, ground_rho : float
    ground : bool
        Add a ground plane (two triangles, kind 0) at z = 0.

    Returns
    -------
    Scene
    """
    rng = np.random.default_rng(seed)
    n = int(rng.poisson(lai * size_m * size_m / leaf_area_m2))
    h = 0.5 * size_m
    centre = np.column_stack([rng.uniform(-h, h, n), rng.uniform(-h, h, n),
                              rng.uniform(z_range[0], z_range[1], n)])
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    helper = np.where(np.abs(normal[:, [2]]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(normal, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(normal, e1)
    side = np.sqrt(4.0 * leaf_area_m2 / np.sqrt(3.0))
    circum = side / np.sqrt(3.0)  # centre-to-vertex distance of an equilateral triangle
    phi = rng.uniform(0.0, 2.0 * np.pi, n)[:, None] + np.array([0.0, 2.0, 4.0]) * np.pi / 3.0
    tri = centre[:, None, :] + circum * (np.cos(phi)[..., None] * e1[:, None, :]
                                         + np.sin(phi)[..., None] * e2[:, None, :])
    leaves = Scene(tri.astype(np.float32), leaf_rho, leaf_tau, KIND_LEAF)
    if not ground:
        return leaves
    return Scene.concat([plane(size_m, 0.0, ground_rho, 0.0, KIND_GROUND), leaves])
