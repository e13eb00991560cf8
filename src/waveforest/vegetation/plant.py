"""What a species model returns: the geometry of its parts, before optics are attached."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_EMPTY = np.empty((0, 3, 3), dtype=np.float32)


@dataclass
class Plant:
    """Triangles of one vegetation instance, by part.

    Attributes
    ----------
    leaves : (n, 3, 3) float32, m
        Leaves, leaflets, needle-shoot planes, grass blades (kind 1).
    leaf_area_m2 : float
        One-sided area of ``leaves`` as designed (the sum of the placed leaf areas).
    wood : (m, 3, 3) float32, m
        Stems, branches, canes, residue pieces (kind 2).
    surface : (k, 3, 3) float32, m
        A height-field surface (soil, sand, stone, moss or lichen carpet).
    n_plants : int
        Trees, shoots, tufts, stems or pieces in the instance.
    element_size_m : float
        Largest extent of one foliage element (leaf length plus petiole), or of the surface
        relief: the scale within which the scene top equals the requested height.
    """

    leaves: np.ndarray = field(default_factory=lambda: _EMPTY)
    leaf_area_m2: float = 0.0
    wood: np.ndarray = field(default_factory=lambda: _EMPTY)
    surface: np.ndarray = field(default_factory=lambda: _EMPTY)
    n_plants: int = 0
    element_size_m: float = 0.0


def lognormal_areas(n: int, total: float, cv: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` positive leaf areas with relative SD ``cv`` summing exactly to ``total``.

    Returns
    -------
    (n,) float64, m^2
    """
    if cv > 0:
        s = np.sqrt(np.log1p(cv * cv))
        a = rng.lognormal(-0.5 * s * s, s, size=n)
    else:
        a = np.ones(n)
    return a * (total / a.sum())


def isotropic(n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` unit vectors uniform on the sphere, (n, 3) float64."""
    z = rng.uniform(-1.0, 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def unit_dirs(zenith, azimuth) -> np.ndarray:
    """Unit vectors from zenith and azimuth angles (rad), (n, 3) float64."""
    zenith = np.asarray(zenith, dtype=np.float64)
    azimuth = np.asarray(azimuth, dtype=np.float64)
    s = np.sin(zenith)
    return np.stack([s * np.cos(azimuth), s * np.sin(azimuth), np.cos(zenith)], axis=-1)


def horizontal(azimuth) -> np.ndarray:
    """Horizontal unit vectors of the given azimuths (rad), (n, 3) float64."""
    azimuth = np.asarray(azimuth, dtype=np.float64)
    return np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros_like(azimuth)], axis=-1)


def piecewise_profile(x, base: float, peak_pos: float, top: float) -> np.ndarray:
    """Relative size along a shoot: linear from ``base`` at x = 0 to 1 at ``peak_pos``, then
    linear to ``top`` at x = 1."""
    x = np.asarray(x, dtype=np.float64)
    rise = base + (1.0 - base) * (x / peak_pos) if peak_pos > 0 else np.ones_like(x)
    fall = 1.0 + (top - 1.0) * (x - peak_pos) / (1.0 - peak_pos) if peak_pos < 1 else np.ones_like(x)
    return np.where(x < peak_pos, rise, fall)
