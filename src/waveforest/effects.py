"""The catalogue of physical effects that the base model of Hovi & Korpela (2014) lacks.

Each effect is set by one number; ``OFF`` is the value that switches it off. The virtual
campaign can hide them in its "real" data (``waveforest synthesize --effect NAME=VALUE``),
and ``diagnose`` adds them to the simulation model. The physics lives where it acts:

================  =======  ==========  ===========================================================
name              off      applied in  meaning of the value
================  =======  ==========  ===========================================================
understory        0        vegetation  LAI of a grass/seedling layer (``UNDERSTORY_HEIGHT_M`` tall)
                                       under trees; 0 = the paper's empty crown-base gap
clumping          0        vegetation  radius of the shoot clusters, m (Thomas process); 0 = the
                                       paper's uniform random shoot positions
xy_error          0        geometry    SD of the horizontal georeferencing error of the recorded
                                       beams (trajectory and points), m
specular          0        mcrt        fraction of the leaf reflectance that is specular (Phong
                                       lobe), the rest Lambertian; 0 = bi-Lambertian leaves
hotspot           1        mcrt        factor on first-order returns from vegetation elements
                                       (coherent backscatter); 1 = none
lad_shift         0        vegetation  shift of the mean leaf inclination angle, degrees
leaf_albedo       1        vegetation  scale on leaf rho and tau
noise_autocorr    0        sensor      AR(1) coefficient of the waveform noise (same marginal SD)
nonlinearity      0        sensor      detector saturation level, DN above the noise mean:
                                       v -> L tanh(v / L); 0 = linear
trigger_loss      0        sensor      fraction of sigma(t), earliest first, lost before the
                                       trigger (energy intercepted without triggering an echo)
================  =======  ==========  ===========================================================

Test values (``Effect.test_value``: what tests and ``diagnose`` hide in a campaign) are
realistic magnitudes, meant to move a Table 3 feature mean by more than 3 standard errors in
a campaign with the paper's pulse counts (tests/test_campaign_agreement.py prints each
effect's largest shift; the recorded shifts are in docs/validation.md, "Campaign agreement
and effect sizes"):

- ``understory`` 2.5: the grass/herb/seedling layer of boreal clear-cuts and young stands
  (Calamagrostis, Deschampsia, Epilobium, tree seedlings) reaches a green LAI of about 1-3 by
  mid-summer, so 2.5 is a dense but common layer; the bound 4 is the densest grass. (With a
  bound of 3 a fit of a hidden 2.5 could stop at the bound by noise alone, and the search
  does not name a fit at its range's far bound: docs/validation.md, Near the stem.) The
  selection keeps a tree's pulses only with a first echo above 1 m and the birch waveform
  features only above 1.5 m (docs/method.md §(i1), i4), so in the crown pulses the layer shows
  through multiple scattering alone; the pulses that reach the ground through gaps in the
  crowns (first echo under 1 m within 0.5 m of the stem) see it directly, and ``diagnose``
  compares them as a stratum of their own (``diagnose.below_crown``).
- ``clumping`` 0.15 m: the value is the SD of the Thomas-process displacement around a
  cluster centre (vegetation/placement.py), so a *smaller* radius is *stronger* clumping
  (radius >> plant spacing is uniform again). Raspberry canes rise from one root crown and
  fireweed and grass shoots from short rhizome branches, a few dm across: at 0.15 m about
  68 % of a cluster's shoots lie within 0.15 m of its centre along each axis (one SD).
- ``xy_error`` 0.25 m: the SD of the horizontal georeferencing error of the recorded data
  relative to the field positions, the paper's "typical XY error 0.20-0.25 m"
  (docs/method.md §(a), j). In the campaign it is a drift of the GNSS/INS solution that moves
  the recorded trajectory and points together (campaign/flight.py), so that ``simulate``
  traces each recorded beam where the real one was not; in the model, ``simulate`` shifts
  each traced beam by a drift of that SD per axis, correlated in GPS time over 10 s
  (:func:`waveforest.model.forward.georeferencing_drift`), so that the pulses of one pass over
  a sample move together.
"""

from __future__ import annotations

from dataclasses import dataclass

from waveforest.errors import WaveforestError


@dataclass(frozen=True)
class Effect:
    """One effect: its name, off value, a realistic test value, search bounds and stage."""

    name: str
    off: float
    test_value: float
    bounds: tuple[float, float]
    stage: str
    description: str


CATALOGUE: dict[str, Effect] = {
    e.name: e
    for e in [
        Effect("understory", 0.0, 2.5, (0.0, 4.0), "vegetation", "LAI of a grass/seedling layer under trees"),
        Effect("clumping", 0.0, 0.15, (0.05, 0.8), "vegetation", "shoot cluster radius, m"),
        Effect("xy_error", 0.0, 0.25, (0.0, 0.6), "geometry", "horizontal georeferencing error SD, m"),
        Effect("specular", 0.0, 0.3, (0.0, 0.8), "mcrt", "specular fraction of the leaf reflectance"),
        Effect("hotspot", 1.0, 1.3, (1.0, 2.0), "mcrt", "first-order enhancement factor of vegetation"),
        Effect("lad_shift", 0.0, 15.0, (-30.0, 30.0), "vegetation", "shift of the mean leaf angle, degrees"),
        Effect("leaf_albedo", 1.0, 0.85, (0.6, 1.2), "vegetation", "scale on leaf rho and tau"),
        Effect("noise_autocorr", 0.0, 0.7, (0.0, 0.95), "sensor", "AR(1) coefficient of the noise"),
        Effect("nonlinearity", 0.0, 150.0, (50.0, 1000.0), "sensor", "detector saturation level, DN"),
        Effect("trigger_loss", 0.0, 0.15, (0.0, 0.5), "sensor", "fraction of sigma lost before the trigger"),
    ]
}

UNDERSTORY_HEIGHT_M = 0.4
"""Height of the understory layer switched on by ``understory``, m."""

SPECULAR_PHONG_EXPONENT = 40.0
"""Phong exponent of the specular leaf lobe (``specular``); a glossy leaf cuticle."""


def parse_effects(items: dict | list[str] | tuple[str, ...] | None) -> dict[str, float]:
    """Effects from a mapping or from ``NAME=VALUE`` strings; unknown names are an error."""
    if not items:
        return {}
    pairs: dict[str, float] = {}
    if isinstance(items, dict):
        raw = items.items()
    else:
        raw = []
        for item in items:
            if "=" not in item:
                raise WaveforestError(f"effect {item!r}: expected NAME=VALUE")
            k, v = item.split("=", 1)
            raw.append((k.strip(), v.strip()))
    for name, value in raw:
        if name not in CATALOGUE:
            raise WaveforestError(f"effect {name!r}: unknown; expected one of {', '.join(CATALOGUE)}")
        try:
            pairs[name] = float(value)
        except (TypeError, ValueError):
            raise WaveforestError(f"effect {name}: value {value!r} is not a number") from None
    return pairs


def active(effects: dict[str, float]) -> dict[str, float]:
    """The effects whose value differs from their off value."""
    return {k: v for k, v in effects.items() if v != CATALOGUE[k].off}
