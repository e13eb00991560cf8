"""The true scenes of the campaign's sites, and tracing every pulse of a site in one call.

* A field sample is one vegetation instance (:func:`waveforest.vegetation.build_scene`) at
  the sample's species and field height, with the campaign's true vegetation effects
  (``understory``, ``clumping``, ``lad_shift``, ``leaf_albedo``). It is built once and every
  pulse of every dataset over it is traced on it: the same plant is seen by every flight of
  a year.
* A reference target is a Lambertian square of its true reflectance (kind ground, tau 0)
  centred on the target; a small target (the 5 x 5 m tarps) lies :data:`TARP_LIFT_M` above a
  ground square of ``on_ground_rho`` so that pulses at its edge see both.

Scene coordinates are local (x east, y north, z up) with the origin at the site's position
and ground elevation; beams are the pulses' true sensor positions minus that origin. The MCRT
effects ``specular`` and ``hotspot`` are passed to :func:`waveforest.mcrt.trace`.
"""

from __future__ import annotations

import numpy as np

from waveforest.rng import stream_seed31
from waveforest.scene import Scene
from waveforest.vegetation import build_scene

TARP_LIFT_M = 0.003
"""Height of a tarp above the ground it lies on, m (its thickness; avoids coplanar faces)."""

GROUND_MARGIN_M = 3.0
"""A ground square around a small target reaches this far beyond any pulse's viewed circle, m."""

TARGET_RAYS = 1000
"""Rays per pulse on planar targets: a Lambertian plane returns every ray's first order exactly
(total sigma = rho cos(theta) / pi whatever the ray count); the rays only sample the spread of
path lengths across the footprint, which the 7-10 ns pulse smooths out."""


def _square(side: float, z: float, rho: float) -> Scene:
    h = side / 2.0
    tri = np.array([[[-h, -h, z], [h, -h, z], [h, h, z]],
                    [[-h, -h, z], [h, h, z], [-h, h, z]]], dtype=np.float32)
    return Scene(tri, np.float32(rho), np.float32(0.0), np.uint8(0))


def target_scene(true_rho: float, side_m: float, on_ground_rho: float | None, reach_m: float) -> Scene:
    """A planar target (module docstring).

    Parameters
    ----------
    true_rho : float
        Lambertian reflectance of the target.
    side_m : float
        Side of the target square, m.
    on_ground_rho : float or None
        Reflectance of the ground around a small target; None/NaN = the target alone.
    reach_m : float
        Largest distance from the centre that a pulse's viewed circle reaches, m.
    """
    top = _square(side_m, 0.0, true_rho)
    if on_ground_rho is None or not np.isfinite(on_ground_rho):
        if side_m / 2 < reach_m:
            top = _square(2 * (reach_m + GROUND_MARGIN_M), 0.0, true_rho)
        return top
    ground = _square(2 * (reach_m + GROUND_MARGIN_M), 0.0, float(on_ground_rho))
    return Scene.concat([_square(side_m, TARP_LIFT_M, true_rho), ground])


def sample_scene(species: str, height_m: float, seed: int, sample_id: str, *, ground_rho: float,
                 lai_jitter: float, vegetation_effects: dict[str, float]) -> Scene:
    """The one vegetation instance of a field sample (module docstring).

    Parameters
    ----------
    species : str
        Species slug.
    height_m : float
        Field height, m.
    seed : int
        Master seed (the instance's own seed derives from it and ``sample_id``).
    sample_id : str
    ground_rho, lai_jitter : float
        Config ``vegetation`` section.
    vegetation_effects : dict
        ``understory``, ``clumping``, ``lad_shift``, ``leaf_albedo`` (missing = off).
    """

    return build_scene(species, float(height_m), stream_seed31(seed, "scene", sample_id), ground_rho=ground_rho,
                       lai_jitter=lai_jitter, **vegetation_effects)
