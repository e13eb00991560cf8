"""Leaf angle distributions (LAD): densities, exact sampling, G-function.

The leaf inclination angle theta in [0, pi/2] is the angle between the leaf normal and the
vertical; azimuths are uniform (docs/method.md §(g)). Densities per radian, integrating to 1:

==============  ============================  =========================================
name            f(theta)                      CDF F(theta)
==============  ============================  =========================================
planophile      (2/pi)(1 + cos 2 theta)        (2/pi)(theta + sin(2 theta)/2)
erectophile     (2/pi)(1 - cos 2 theta)        (2/pi)(theta - sin(2 theta)/2)
plagiophile     (2/pi)(1 - cos 4 theta)        (2/pi)(theta - sin(4 theta)/4)
extremophile    (2/pi)(1 + cos 4 theta)        (2/pi)(theta + sin(4 theta)/4)
uniform         2/pi                          2 theta/pi
spherical       sin theta                     1 - cos theta
beta            (2/pi) t^(nu-1) (1-t)^(mu-1) / B(mu, nu),  t = 2 theta/pi
==============  ============================  =========================================

de Wit (1965) types as tabulated by Weiss et al. (2004); the two-parameter beta form is that
of Goel & Strebel (1984) (mean t = nu / (mu + nu)). Sampling is exact: closed-form inverse CDF
(uniform, spherical), inverse CDF solved to machine precision by a safeguarded Newton
iteration (the four trigonometric types, Numba kernel :func:`_invert_dewit`), or numpy's
exact beta sampler (beta). The limit of the beta form at a mean of 0 or 90 degrees is
"all leaves at that angle" (name ``fixed``).

A *mean leaf angle* (``build_scene(mean_leaf_angle=...)``) and a *shift* of it (effect
``lad_shift``) are realised by the beta form with the same concentration k = mu + nu as the
species' LAD (k from matching the mean and variance of t, Wang et al. 2007), so that the
shape stays that of the species and only the mean moves; the mean is clipped to [0, 90] deg.

G-function (Ross 1981): G(theta_v) = int_0^{pi/2} f(theta_L) A(theta_v, theta_L) d theta_L,
A = cos theta_v cos theta_L if |cot theta_v cot theta_L| >= 1, else
cos theta_v cos theta_L [1 + (2/pi)(tan psi - psi)], psi = arccos(cot theta_v cot theta_L).
A random canopy of leaf area index L then has a gap probability exp(-G L / cos theta_v)
(Nilson 1971).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

DEWIT = ("planophile", "erectophile", "plagiophile", "extremophile")
LAD_NAMES = DEWIT + ("uniform", "spherical")
"""Names of the de Wit (1965) distributions; plus ``beta`` and ``fixed`` built by methods."""

_CODE = {name: i for i, name in enumerate(DEWIT)}
# F(theta) = (2/pi) (theta + _SIGN * sin(_FREQ theta) / _FREQ) for the four trigonometric types
_SIGN = np.array([1.0, -1.0, -1.0, 1.0])
_FREQ = np.array([2.0, 2.0, 4.0, 4.0])

INVERSE_TOL_RAD = 1e-14
"""Convergence tolerance of the inverse-CDF iteration, rad."""

_MAX_ITER = 200
HALF_PI = 0.5 * math.pi
EDGE_DEG = 1e-9
"""Means within this of 0 or 90 degrees give the degenerate ``fixed`` distribution."""


@njit(cache=True, nogil=True)
def _invert_dewit(u, table, sign, freq):  # pragma: no cover - compiled; tested against reference
    """theta with F(theta) = u for F = (2/pi)(theta + sign sin(freq theta)/freq).

    ``table`` holds theta at u = 0, 1/m, ..., 1 (m + 1 values, or a single value to start
    from pi/4); its linear interpolation is the Newton start. Safeguarded Newton: the bracket
    [lo, hi], initially [0, pi/2], shrinks every step and a Newton step leaving it (or a zero
    density) is replaced by bisection, so convergence is guaranteed.
    """
    out = np.empty(u.shape[0])
    c = 2.0 / math.pi
    m = table.shape[0] - 1
    for i in range(u.shape[0]):
        target = u[i]
        lo, hi = 0.0, 0.5 * math.pi
        if m > 0:
            j = min(int(target * m), m - 1)
            w = target * m - j
            th = table[j] + w * (table[j + 1] - table[j])
        else:
            th = 0.25 * math.pi
        for _ in range(_MAX_ITER):
            g = c * (th + sign * math.sin(freq * th) / freq) - target
            if g == 0.0:
                break
            if g > 0.0:
                hi = th
            else:
                lo = th
            f = c * (1.0 + sign * math.cos(freq * th))
            step = g / f if f > 0.0 else 0.0
            if f > 0.0 and abs(step) <= INVERSE_TOL_RAD:
                th = min(max(th - step, lo), hi)
                break
            nxt = th - step
            if f <= 0.0 or not (lo < nxt < hi):
                nxt = 0.5 * (lo + hi)
            if hi - lo <= INVERSE_TOL_RAD:
                th = nxt
                break
            th = nxt
        out[i] = th
    return out


_TABLE_SIZE = 1024
"""Intervals of the inverse-CDF table that gives the Newton start."""


@functools.cache
def _inverse_table(k: int) -> np.ndarray:
    u = np.linspace(0.0, 1.0, _TABLE_SIZE + 1)
    return _invert_dewit(u, np.empty(1), float(_SIGN[k]), float(_FREQ[k]))


def invert_dewit_cdf(name: str, u) -> np.ndarray:
    """Inverse CDF of a trigonometric de Wit LAD.

    Parameters
    ----------
    name : {'planophile', 'erectophile', 'plagiophile', 'extremophile'}
    u : (n,) float64 in [0, 1]
        Probabilities.

    Returns
    -------
    (n,) float64, rad
        Leaf inclinations theta with F(theta) = u, to ``INVERSE_TOL_RAD``.
    """
    if name not in _CODE:
        raise ValueError(f"invert_dewit_cdf: name must be one of {DEWIT}, got {name!r}")
    u = np.ascontiguousarray(u, dtype=np.float64)
    if u.ndim != 1:
        raise ValueError(f"invert_dewit_cdf: u must be 1-D, got shape {u.shape}")
    if u.size and (not np.all(np.isfinite(u)) or u.min() < 0.0 or u.max() > 1.0):
        raise ValueError("invert_dewit_cdf: u must be finite and in [0, 1]")
    k = _CODE[name]
    return _invert_dewit(u, _inverse_table(k), float(_SIGN[k]), float(_FREQ[k]))


def _psi_projection(view: float, leaf: np.ndarray) -> np.ndarray:
    """A(theta_v, theta_L) of the G-function for an array of leaf inclinations (rad)."""
    cv, cl = math.cos(view), np.cos(leaf)
    with np.errstate(divide="ignore", invalid="ignore"):
        cot = (1.0 / math.tan(view) if view > 0 else np.inf) / np.tan(leaf)
    out = cv * cl
    m = np.abs(cot) < 1.0
    if np.any(m):
        psi = np.arccos(cot[m])
        # cos(view) cos(leaf) tan(psi) -> (2/pi) sin(view) sin(leaf) sin(psi) (no 0*inf at 90 deg)
        sv, sl = math.sin(view), np.sin(leaf[m])
        out[m] = cv * cl[m] * (1.0 - 2.0 / math.pi * psi) + 2.0 / math.pi * sv * sl * np.sin(psi)
    return out


@dataclass(frozen=True)
class LeafAngleDistribution:
    """A leaf inclination distribution.

    Attributes
    ----------
    name : str
        One of ``LAD_NAMES``, ``'beta'`` or ``'fixed'``.
    mu, nu : float
        Beta parameters (Goel & Strebel 1984) for ``'beta'``; for ``'fixed'`` ``mu`` is the
        angle, rad. NaN otherwise.
    """

    name: str
    mu: float = float("nan")
    nu: float = float("nan")

    def __post_init__(self) -> None:
        if self.name in LAD_NAMES:
            return
        if self.name == "beta":
            if not (self.mu > 0 and self.nu > 0 and np.isfinite(self.mu + self.nu)):
                raise ValueError(f"beta LAD: mu and nu must be positive, got {self.mu}, {self.nu}")
        elif self.name == "fixed":
            if not (0.0 <= self.mu <= HALF_PI):
                raise ValueError(f"fixed LAD: angle must be in [0, pi/2] rad, got {self.mu}")
        else:
            raise ValueError(f"LAD {self.name!r}: expected one of {LAD_NAMES + ('beta', 'fixed')}")

    # --- constructors -------------------------------------------------------------------------
    @staticmethod
    def beta_with_mean(mean_deg: float, concentration: float) -> LeafAngleDistribution:
        """Beta LAD with mean inclination ``mean_deg`` and mu + nu = ``concentration``.

        The mean is clipped to [0, 90]; at the ends the distribution is ``fixed``.
        """
        if not (np.isfinite(mean_deg) and concentration > 0):
            raise ValueError(f"beta LAD: need a finite mean and positive concentration, "
                             f"got {mean_deg}, {concentration}")
        mean_deg = float(np.clip(mean_deg, 0.0, 90.0))
        if mean_deg <= EDGE_DEG or mean_deg >= 90.0 - EDGE_DEG:
            return LeafAngleDistribution("fixed", mu=math.radians(round(mean_deg)))
        t = mean_deg / 90.0
        return LeafAngleDistribution("beta", mu=concentration * (1.0 - t), nu=concentration * t)

    def with_mean(self, mean_deg: float) -> LeafAngleDistribution:
        """The beta form with this LAD's concentration and the given mean, degrees."""
        return LeafAngleDistribution.beta_with_mean(mean_deg, self.concentration)

    def shifted(self, shift_deg: float) -> LeafAngleDistribution:
        """This LAD with its mean moved by ``shift_deg`` (beta form; no-op for a zero shift)."""
        if shift_deg == 0.0:
            return self
        return self.with_mean(self.mean_deg + shift_deg)

    # --- moments ------------------------------------------------------------------------------
    @property
    def moments_t(self) -> tuple[float, float]:
        """Mean and variance of t = 2 theta / pi."""
        if self.name == "beta":
            k = self.mu + self.nu
            m = self.nu / k
            return m, m * (1 - m) / (k + 1)
        if self.name == "fixed":
            return self.mu / HALF_PI, 0.0
        return _dewit_moments(self.name)

    @property
    def mean_deg(self) -> float:
        """Mean leaf inclination, degrees."""
        return 90.0 * self.moments_t[0]

    @property
    def concentration(self) -> float:
        """mu + nu of the moment-matched beta form (Wang et al. 2007); inf for ``fixed``."""
        m, v = self.moments_t
        if v <= 0:
            return float("inf")
        return m * (1 - m) / v - 1.0

    # --- density, CDF, sampling ---------------------------------------------------------------
    def pdf(self, theta) -> np.ndarray:
        """Density per radian at ``theta`` (rad); not defined for ``fixed``."""
        th = np.asarray(theta, dtype=np.float64)
        inside = (th >= 0) & (th <= HALF_PI)
        c = 2.0 / math.pi
        if self.name in _CODE:
            k = _CODE[self.name]
            f = c * (1.0 + _SIGN[k] * np.cos(_FREQ[k] * th))
        elif self.name == "uniform":
            f = np.full_like(th, c)
        elif self.name == "spherical":
            f = np.sin(th)
        elif self.name == "beta":
            from scipy import special

            t = np.clip(th / HALF_PI, 0.0, 1.0)
            with np.errstate(divide="ignore"):
                f = c * np.exp((self.nu - 1) * np.log(t) + (self.mu - 1) * np.log1p(-t)
                               - special.betaln(self.mu, self.nu))
        else:
            raise ValueError("a fixed LAD has no density")
        return np.where(inside, f, 0.0)

    def cdf(self, theta) -> np.ndarray:
        """Cumulative distribution at ``theta`` (rad)."""
        th = np.clip(np.asarray(theta, dtype=np.float64), 0.0, HALF_PI)
        if self.name in _CODE:
            k = _CODE[self.name]
            return 2.0 / math.pi * (th + _SIGN[k] * np.sin(_FREQ[k] * th) / _FREQ[k])
        if self.name == "uniform":
            return th / HALF_PI
        if self.name == "spherical":
            return 1.0 - np.cos(th)
        if self.name == "beta":
            from scipy import special

            return special.betainc(self.nu, self.mu, th / HALF_PI)
        return (th >= self.mu).astype(np.float64)

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` exact draws of the leaf inclination, (n,) float64, rad."""
        if self.name == "fixed":
            return np.full(n, self.mu)
        if self.name == "beta":
            return HALF_PI * rng.beta(self.nu, self.mu, size=n)
        u = rng.random(n)
        if self.name == "uniform":
            return HALF_PI * u
        if self.name == "spherical":
            return np.arccos(1.0 - u)
        return invert_dewit_cdf(self.name, u)

    # --- G-function ---------------------------------------------------------------------------
    def g(self, view_zenith: float) -> float:
        """Mean projection G(theta_v) of unit leaf area on a plane normal to the view (Ross 1981).

        Parameters
        ----------
        view_zenith : float, rad, in [0, pi/2]
        """
        view = float(view_zenith)
        if not (0.0 <= view <= HALF_PI):
            raise ValueError(f"G: view zenith must be in [0, pi/2] rad, got {view}")
        if self.name == "fixed":
            return float(_psi_projection(view, np.array([self.mu]))[0])
        return _g_integral(self, view)


@functools.cache
def _dewit_moments(name: str) -> tuple[float, float]:
    from scipy import integrate  # heavy to import, and few commands integrate

    lad = LeafAngleDistribution(name)
    m1 = integrate.quad(lambda th: (th / HALF_PI) * lad.pdf(th), 0, HALF_PI, epsabs=1e-13)[0]
    m2 = integrate.quad(lambda th: (th / HALF_PI) ** 2 * lad.pdf(th), 0, HALF_PI, epsabs=1e-13)[0]
    return m1, m2 - m1 * m1


@functools.lru_cache(maxsize=256)
def _g_integral(lad: LeafAngleDistribution, view: float) -> float:
    from scipy import integrate

    def f(th):
        return float(lad.pdf(th) * _psi_projection(view, np.array([th]))[0])

    brk = [HALF_PI - view] if 0.0 < view < HALF_PI else None
    return integrate.quad(f, 0.0, HALF_PI, points=brk, limit=200, epsabs=1e-12)[0]


def lad_by_name(name: str) -> LeafAngleDistribution:
    """The de Wit distribution ``name`` (one of ``LAD_NAMES``)."""
    if name not in LAD_NAMES:
        raise ValueError(f"LAD {name!r}: expected one of {', '.join(LAD_NAMES)}")
    return LeafAngleDistribution(name)


def sample_normals(lad: LeafAngleDistribution, n: int, rng: np.random.Generator) -> np.ndarray:
    """Unit leaf normals (upper hemisphere) with inclinations from ``lad`` and uniform azimuths.

    Returns
    -------
    (n, 3) float64
    """
    theta = lad.sample(n, rng)
    phi = rng.uniform(0.0, 2.0 * math.pi, n)
    s = np.sin(theta)
    return np.stack([s * np.cos(phi), s * np.sin(phi), np.cos(theta)], axis=1)
