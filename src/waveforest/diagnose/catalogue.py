"""The effect catalogue as one-parameter components of the simulation model.

:mod:`waveforest.effects` names the effects, their off values, realistic test values and
bounds, and where the physics lives. This module adds what the diagnosis needs:

* a *search coordinate* u in [0, 1] per effect, on which the 1-D search runs. It is linear
  in the value over the effect's bounds, except for the effects whose strength falls as
  their value grows and whose "off" lies at infinity (:data:`INVERSE_SCALE`), searched on
  u = v_min / v, so that u = 0 is "off" and the effect grows smoothly with u:
  ``nonlinearity`` (saturation level L: v -> L tanh(v / L) departs from v as 1 / L^2) and
  ``clumping`` (Thomas cluster radius r: a small radius is tight clumping, a radius much
  larger than the plant spacing is uniform placement again; the value 0 stands for "off");
* the grid of values of a candidate (always containing the off value, which is the
  current model itself and needs no extra simulation);
* which stage of the simulation each effect acts in, and therefore whether a candidate
  can reuse the vegetation instances of the current model: ``mcrt``, ``sensor`` and
  ``geometry`` effects trace the same plants as the model without them, so a simulator may
  keep its scenes (and, for ``sensor`` effects, even its sigma(t)) across their values;
* the *signature* of an effect: how its test value moves each feature in each
  dataset x species cell, in pooled SDs (:func:`signature`).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from waveforest.diagnose import gap as _gap
from waveforest.effects import CATALOGUE, Effect
from waveforest.errors import WaveforestError

VEGETATION_EFFECTS = tuple(n for n, e in CATALOGUE.items() if e.stage == "vegetation")
"""Effects that change the plants (a new value needs new vegetation instances)."""

INVERSE_SCALE = {"nonlinearity", "clumping"}
"""Effects searched on u = lower bound / value (off value 0 = infinitely far)."""

UNITS: dict[str, str] = {
    "understory": "LAI", "clumping": "m", "xy_error": "m", "specular": "share of rho", "hotspot": "factor",
    "lad_shift": "deg", "leaf_albedo": "factor", "noise_autocorr": "AR(1)", "nonlinearity": "DN",
    "trigger_loss": "share of sigma",
}
"""Unit of each effect's value (:mod:`waveforest.effects` states them in words)."""


def effect(name: str) -> Effect:
    """The catalogue entry of ``name``; an unknown name is an error naming the choices."""
    try:
        return CATALOGUE[name]
    except KeyError:
        raise WaveforestError(f"effect {name!r}: unknown; expected one of {', '.join(CATALOGUE)}") from None


def to_u(name: str, value: float) -> float:
    """Search coordinate of an effect value (0 ... 1 over the bounds; off may be inside).

    Parameters
    ----------
    name : str
        Effect name.
    value : float
        Effect value in the units of :mod:`waveforest.effects`.
    """
    e = effect(name)
    lo, hi = e.bounds
    if name in INVERSE_SCALE:
        return 0.0 if value == e.off or not math.isfinite(value) else float(lo / value)
    return float((value - lo) / (hi - lo))


def from_u(name: str, u: float) -> float:
    """Effect value of a search coordinate (inverse of :func:`to_u`); u is clipped to [0, 1]."""
    e = effect(name)
    lo, hi = e.bounds
    u = float(np.clip(u, 0.0, 1.0))
    if name in INVERSE_SCALE:
        return e.off if u <= 0.0 else float(lo / u)
    return float(lo + u * (hi - lo))


def value_interval(name: str, u_low: float, u_high: float) -> tuple[float, float]:
    """Value interval of a u interval; ``inf`` where the inverse scale reaches "off"."""
    a, b = (from_u(name, u) for u in (u_low, u_high))
    if name in INVERSE_SCALE:
        a = math.inf if u_low <= 0 else a
        b = math.inf if u_high <= 0 else b
    return (min(a, b), max(a, b))


def off_u(name: str) -> float:
    """Search coordinate of the off value."""
    return to_u(name, effect(name).off)


def grid(name: str, n_values: int) -> np.ndarray:
    """``n_values`` search coordinates evenly spread over [0, 1], the one nearest the off
    value moved onto it (so the current model is always a grid point).

    Returns
    -------
    (n_values,) float64, sorted
    """
    if n_values < 3:
        raise ValueError(f"a candidate needs at least 3 grid values, got {n_values}")
    u = np.linspace(0.0, 1.0, n_values)
    u0 = off_u(name)
    if 0.0 <= u0 <= 1.0:
        u[np.argmin(np.abs(u - u0))] = u0
    return np.sort(u)


def with_effect(effects: dict[str, float], name: str, value: float) -> dict[str, float]:
    """``effects`` plus ``name = value``; the off value removes ``name`` (canonical form,
    so that "effect at its off value" and "model without the effect" are the same model)."""
    out = {k: float(v) for k, v in effects.items() if k != name}
    if value != effect(name).off:
        out[name] = float(value)
    return dict(sorted(out.items()))


def reuses_vegetation(name: str) -> bool:
    """Whether a simulator may keep the current model's plants across this effect's values."""
    return effect(name).stage != "vegetation"


def signature(
    off: pd.DataFrame,
    on: pd.DataFrame,
    *,
    features: tuple[str, ...] = _gap.FEATURES,
    floors: dict[str, float] | None = None,
    min_pulses: int = _gap.MIN_CELL_PULSES,
    min_samples: int = _gap.MIN_CELL_SAMPLES,
) -> pd.DataFrame:
    """How an effect moves the features: simulation with it (``on``) against without (``off``).

    Both tables should come from the same pulses and seed (common random numbers), so the
    difference is the effect and not simulation noise.

    Returns
    -------
    DataFrame
        One row per dataset x species x feature: mean_off, mean_on, sd_off, sd_on,
        shift_sd (= d of ``on`` against ``off``, pooled SDs), log_sd_ratio, n.
    """
    data = _gap.GapData.build(off, on, features=features, floors=floors,
                              min_pulses=min_pulses, min_samples=min_samples)
    st = _gap.cell_statistics(data)
    rows = []
    for c, (ds, sp) in enumerate(data.cells.itertuples(index=False)):
        for k, f in enumerate(data.features):
            rows.append({
                "dataset": ds, "species": sp, "feature": f,
                "mean_off": st["mean_real"][c, k], "mean_on": st["mean_sim"][c, k],
                "sd_off": st["sd_real"][c, k], "sd_on": st["sd_sim"][c, k],
                "shift_sd": st["d"][c, k], "log_sd_ratio": st["log_sd_ratio"][c, k],
                "n": int(st["n_real"][c, k]),
            })
    return pd.DataFrame(rows)
