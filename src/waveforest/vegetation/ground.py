"""Ground: a Lambertian plane, or a surface with micro-relief.

The plane (docs/method.md §(g): rho 0.30, tau 0) is two triangles covering the plot at z = 0 with
upward normals. Micro-relief (abiotic surfaces, moss and lichen carpets, soil under logging
residue) is a periodic Gaussian random field on a regular grid: white noise filtered in
Fourier space to a Gaussian covariance C(r) = s^2 exp(-r^2 / l^2) (spectral density
proportional to exp(-k^2 l^2 / 4)), then shifted to zero mean and scaled to an RMS of
exactly s. Each grid cell gives two triangles.
"""

from __future__ import annotations

import numpy as np

from waveforest.constants import KIND_GROUND
from waveforest.scene import Scene
from waveforest.vegetation.params import PLOT_HALF_M


def ground_plane(rho: float, half: float = PLOT_HALF_M) -> Scene:
    """The flat ground: two triangles over [-half, half]^2 at z = 0, kind 0, tau 0."""
    h = half
    tri = np.array(
        [[[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0]],
         [[-h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]]],
        dtype=np.float32,
    )
    return Scene(tri, rho, 0.0, KIND_GROUND)


def relief_field(rng: np.random.Generator, rms: float, corr: float, n: int,
                 half: float = PLOT_HALF_M) -> np.ndarray:
    """A periodic Gaussian random height field on an n x n grid.

    Parameters
    ----------
    rms : float, m
        Standard deviation of the heights (realised exactly; 0 gives a flat field).
    corr : float, m
        Correlation length l of the Gaussian covariance (> 0).
    n : int
        Grid points per side (spacing 2 half / n).

    Returns
    -------
    (n, n) float64, m
        Heights with zero mean; index [iy, ix].
    """
    if rms < 0 or corr <= 0 or n < 2:
        raise ValueError(f"relief_field: need rms >= 0, corr > 0, n >= 2; got {rms}, {corr}, {n}")
    noise = rng.standard_normal((n, n))
    if rms == 0:
        return np.zeros((n, n))
    k = 2.0 * np.pi * np.fft.fftfreq(n, d=2.0 * half / n)
    k2 = k[:, None] ** 2 + k[None, :] ** 2
    field = np.fft.ifft2(np.fft.fft2(noise) * np.exp(-k2 * corr**2 / 8.0)).real
    field -= field.mean()
    sd = field.std()
    return field * (rms / sd) if sd > 0 else field


def heightfield_triangles(z: np.ndarray, half: float = PLOT_HALF_M) -> np.ndarray:
    """Triangles of a periodic height field over the plot (upward normals).

    Parameters
    ----------
    z : (n, n) float64, m
        Heights at grid points x_i = -half + i * 2 half / n (index [iy, ix]); the field is
        periodic, so the row/column at +half repeats the first one.

    Returns
    -------
    (2 n^2, 3, 3) float32, m
    """
    n = z.shape[0]
    if z.shape != (n, n):
        raise ValueError(f"heightfield_triangles: expected a square grid, got {z.shape}")
    zz = np.pad(z, ((0, 1), (0, 1)), mode="wrap")
    g = np.linspace(-half, half, n + 1)
    X, Y = np.meshgrid(g, g)  # [iy, ix]
    P = np.stack([X, Y, zz], axis=-1)
    a, b = P[:-1, :-1], P[:-1, 1:]  # (x, y), (x + 1, y)
    c, d = P[1:, 1:], P[1:, :-1]  # (x + 1, y + 1), (x, y + 1)
    t1 = np.stack([a, b, c], axis=2).reshape(-1, 3, 3)
    t2 = np.stack([a, c, d], axis=2).reshape(-1, 3, 3)
    return np.concatenate([t1, t2]).astype(np.float32)
