"""Laser beams: sensor position, pointing direction and Gaussian footprint (docs/method.md §(d), "Beam").

A beam's irradiance across its axis is Gaussian, E(r) ~ exp(-(2 r / d)^2) with d the 1/e
footprint diameter, so the ray offsets have a per-axis SD of d / (2 sqrt 2).

Two ray geometries, equivalent at the ALS ranges (R >= 500 m, where the footprint changes by
< 1 % over a 6-m-deep scene):

* **diverging** (``range_m`` given, as from :meth:`Beams.from_divergence`): every ray starts at
  the sensor point, its direction perturbed so that it crosses the plane perpendicular to the
  axis at ``range_m`` at its Gaussian offset; the footprint grows linearly with distance.
* **collimated** (``range_m`` NaN, the default): rays parallel to the axis, offset across it
  at the sensor; the footprint is ``footprint_m`` at every distance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

UNIT_TOL = 1e-6
"""Largest accepted | |direction| - 1 | before a direction is refused as not unit."""


def _rows(a, name: str, n: int | None = None) -> np.ndarray:
    x = np.asarray(a, dtype=np.float64)
    if x.ndim == 1 and x.shape == (3,):
        x = x[None, :]
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (n, 3) or (3,), got {x.shape}")
    if n is not None and len(x) not in (1, n):
        raise ValueError(f"{name}: expected {n} rows, got {len(x)}")
    if n is not None and len(x) == 1:
        x = np.repeat(x, n, axis=0)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name}: non-finite values")
    return np.ascontiguousarray(x)


def _column(a, name: str, n: int, allow_nan: bool = False) -> np.ndarray:
    x = np.asarray(a, dtype=np.float64)
    if x.ndim == 0:
        x = np.full(n, float(x))
    if x.shape != (n,):
        raise ValueError(f"{name}: expected a scalar or shape ({n},), got {x.shape}")
    bad = ~np.isfinite(x) if not allow_nan else np.isinf(x)
    if np.any(bad):
        raise ValueError(f"{name}: non-finite values")
    return np.ascontiguousarray(x)


def direction_from_angles(scan_zenith_deg, azimuth_deg) -> np.ndarray:
    """Unit beam directions (sensor -> target) from scan zenith and azimuth.

    Parameters
    ----------
    scan_zenith_deg : scalar or (n,) float, degrees
        Angle between the beam and the nadir (0 = straight down).
    azimuth_deg : scalar or (n,) float, degrees
        Compass azimuth of the beam's horizontal travel, clockwise from north (+y) towards
        east (+x).

    Returns
    -------
    (n, 3) float64
        (sin z sin a, sin z cos a, -cos z).
    """
    z, a = np.broadcast_arrays(np.radians(np.asarray(scan_zenith_deg, float)),
                               np.radians(np.asarray(azimuth_deg, float)))
    d = np.stack([np.sin(z) * np.sin(a), np.sin(z) * np.cos(a), -np.cos(z)], axis=-1)
    return d.reshape(-1, 3)


@dataclass(frozen=True)
class Beams:
    """A batch of laser pulses to trace.

    Attributes
    ----------
    origin : (n, 3) float64, m
        Sensor (transmitter and receiver) positions in scene coordinates.
    direction : (n, 3) float64
        Unit beam axes, sensor -> target.
    footprint_m : (n,) float64, m
        1/e footprint diameter (at ``range_m`` for diverging beams), >= 0.
    range_m : (n,) float64, m, optional
        Distance at which a diverging beam has ``footprint_m``; NaN (default) = collimated.
    """

    origin: np.ndarray
    direction: np.ndarray
    footprint_m: np.ndarray
    range_m: np.ndarray | None = None

    def __post_init__(self) -> None:
        d0, o0 = _rows(self.direction, "direction"), _rows(self.origin, "origin")
        n = max(len(d0), len(o0), np.size(self.footprint_m))
        d, o = _rows(d0, "direction", n), _rows(o0, "origin", n)
        norm = np.linalg.norm(d, axis=1)
        if np.any(np.abs(norm - 1.0) > UNIT_TOL):
            worst = float(np.max(np.abs(norm - 1.0)))
            raise ValueError(f"direction: expected unit vectors (| |d| - 1 | <= {UNIT_TOL}), worst {worst:.3g}")
        d = d / norm[:, None]
        fp = _column(self.footprint_m, "footprint_m", n)
        if np.any(fp < 0):
            raise ValueError("footprint_m: expected >= 0")
        rng = np.full(n, np.nan) if self.range_m is None else _column(self.range_m, "range_m", n, allow_nan=True)
        if np.any(rng <= 0):
            raise ValueError("range_m: expected > 0 (or NaN for a collimated beam)")
        object.__setattr__(self, "origin", o)
        object.__setattr__(self, "direction", np.ascontiguousarray(d))
        object.__setattr__(self, "footprint_m", fp)
        object.__setattr__(self, "range_m", rng)

    def __len__(self) -> int:
        return len(self.direction)

    def __getitem__(self, index) -> Beams:
        idx = np.arange(len(self))[index]
        idx = np.atleast_1d(idx)
        return Beams(self.origin[idx], self.direction[idx], self.footprint_m[idx], self.range_m[idx])

    @property
    def diverging(self) -> np.ndarray:
        """(n,) bool: True where rays diverge from the sensor point (``range_m`` given)."""
        return np.isfinite(self.range_m)

    @classmethod
    def from_divergence(cls, origin, direction, divergence_mrad, range_m) -> Beams:
        """Diverging beams whose 1/e footprint at ``range_m`` is ``range_m * divergence``.

        Parameters
        ----------
        origin, direction : (n, 3) or (3,) float64
        divergence_mrad : scalar or (n,) float, mrad
            Full-angle 1/e beam divergence (ALS60: 0.15 mrad).
        range_m : scalar or (n,) float, m
            Range to the target (e.g. the scene's ground point).
        """
        n = max(len(_rows(direction, "direction")), len(_rows(origin, "origin")),
                np.size(divergence_mrad), np.size(range_m))
        d = _rows(direction, "direction", n)
        div = _column(divergence_mrad, "divergence_mrad", n)
        rng = _column(range_m, "range_m", n)
        if np.any(div < 0):
            raise ValueError("divergence_mrad: expected >= 0")
        return cls(origin, d, rng * div * 1e-3, rng)

    @classmethod
    def toward(cls, target, range_m, scan_zenith_deg=0.0, azimuth_deg=0.0, *,
               footprint_m=None, divergence_mrad=None) -> Beams:
        """Beams aimed at ``target`` from ``range_m`` away, at the given scan zenith and azimuth.

        Give exactly one of ``footprint_m`` (collimated beams of that 1/e diameter) or
        ``divergence_mrad`` (diverging beams, footprint ``range_m * divergence`` at the target).

        Parameters
        ----------
        target : (n, 3) or (3,) float64, m
            Point on each beam axis at distance ``range_m`` from the sensor.
        range_m, scan_zenith_deg, azimuth_deg : scalar or (n,) float
            See :func:`direction_from_angles` for the angles.
        """
        if (footprint_m is None) == (divergence_mrad is None):
            raise ValueError("give exactly one of footprint_m and divergence_mrad")
        d = direction_from_angles(scan_zenith_deg, azimuth_deg)
        tgt = _rows(target, "target")
        n = max(len(d), len(tgt), np.size(range_m))
        d = _rows(d, "direction", n)
        tgt = _rows(tgt, "target", n)
        rng = _column(range_m, "range_m", n)
        origin = tgt - rng[:, None] * d
        if divergence_mrad is not None:
            return cls.from_divergence(origin, d, divergence_mrad, rng)
        return cls(origin, d, footprint_m)


DEFAULT_DIVERGENCE_MRAD = 0.15
"""ALS60 1/e beam divergence, mrad (docs/method.md §(a)): a :class:`BeamSpec` with neither a
footprint nor a divergence."""


@dataclass(frozen=True)
class BeamSpec:
    """One pulse aimed at a target point (:meth:`Beams.toward`).

    Attributes
    ----------
    target : (3,) float, m
        Point on the beam axis at ``range_m`` from the sensor (scene coordinates).
    range_m : float, m
    scan_zenith_deg, azimuth_deg : float, degrees
        As :func:`direction_from_angles`.
    footprint_m, divergence_mrad : float or None
        1/e footprint diameter of a collimated beam (m), or 1/e divergence of a diverging one
        (mrad): at most one; neither = :data:`DEFAULT_DIVERGENCE_MRAD`.
    """

    target: tuple[float, float, float]
    range_m: float
    scan_zenith_deg: float
    azimuth_deg: float
    footprint_m: float | None = None
    divergence_mrad: float | None = None

    def beams(self) -> Beams:
        """The one-pulse :class:`Beams` (ValueError for a footprint and a divergence both given)."""
        divergence = self.divergence_mrad
        if self.footprint_m is None and divergence is None:
            divergence = DEFAULT_DIVERGENCE_MRAD
        return Beams.toward(np.asarray(self.target, float), float(self.range_m), float(self.scan_zenith_deg),
                            float(self.azimuth_deg), footprint_m=self.footprint_m, divergence_mrad=divergence)
