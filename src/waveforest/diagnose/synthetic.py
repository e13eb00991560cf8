"""A cheap synthetic study with known effect signatures (tests, demos, benchmarks).

Not physics: a linear-Gaussian stand-in for the real chain (vegetation -> MCRT -> sensor ->
features) with the same *shape* of data, so that the search logic of :mod:`.search` can be
checked against known answers in milliseconds. Each pulse's feature f is

    x_f = mu_f(species, h) + shift_f(effects) + scale_f(effects) * (s_plant z_plant + s_pulse z_pulse)

with z standard normal. The *real* data draw one ``z_plant`` per field sample (every pulse
of a sample sees the same plant); the simulator draws one per pulse (a new vegetation
instance per pulse, METHOD.md g), so within-sample correlation differs as in the real
study. Effects act on real and simulated pulses through the same functions
(:func:`apply_effects`), with signatures chosen after METHOD.md j (e.g. understory lowers
birch Npeaks and the spread of E; clumping widens the spread of H and Apeak of the low
species, more at small footprints; hotspot raises Apeak and narrows echoes; nonlinearity is
the sensor's tanh saturation) and distinct enough to be identifiable. ``perturb`` adds a
disagreement that no effect can produce (the "unexplained" case).

The simulator draws its random numbers per pulse from ``(seed, dataset, pulse_id,
replicate)``, so the same seed gives the same numbers for every effect value (common random
numbers) and for any subset of pulses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ..effects import CATALOGUE
from .catalogue import to_u
from .gap import FEATURES

SPECIES: dict[str, dict] = {
    # height range (m); per feature (mean at h, SD between plants, SD between pulses)
    "birch": {"h": (2.5, 5.0), "tree": True,
              "H": ("0.75h", 0.30, 0.40), "Npeaks": (1.6, 0.20, 0.40), "Apeak": (80.0, 6.0, 12.0),
              "FWHM": (6.5, 0.40, 0.80), "E": (560.0, 40.0, 80.0)},
    "raspberry": {"h": (0.6, 1.8), "tree": False,
                  "H": ("0.85h", 0.10, 0.15), "Npeaks": (1.2, 0.10, 0.30), "Apeak": (110.0, 6.0, 12.0),
                  "FWHM": (5.6, 0.30, 0.60), "E": (700.0, 40.0, 80.0)},
    "fireweed": {"h": (0.8, 2.5), "tree": False,
                 "H": ("0.80h", 0.15, 0.20), "Npeaks": (1.3, 0.10, 0.30), "Apeak": (100.0, 6.0, 11.0),
                 "FWHM": (5.9, 0.30, 0.70), "E": (640.0, 40.0, 75.0)},
}
"""Toy species: height ranges of Fig. 6 and feature levels of the order of Table 3."""

DATASETS: dict[str, dict] = {
    "2010_12_1": {"year": 2010, "footprint_m": 0.18},
    "2012_10_1": {"year": 2012, "footprint_m": 0.15},
    "2012_27_1": {"year": 2012, "footprint_m": 0.41},
}
"""Toy datasets: name -> year and 1/e footprint (Table 2)."""

_REF_FOOTPRINT_M = 0.18
"""Footprint at which the footprint-dependent toy signatures have their nominal size."""


def apply_effects(keys: pd.DataFrame, effects: dict[str, float]) -> tuple[dict, dict, dict]:
    """Per-pulse shifts, multiplicative factors and noise scales of the toy effects.

    Parameters
    ----------
    keys : DataFrame
        n pulses: species, height_m, footprint_m.
    effects : dict
        Effect name -> value (:mod:`waveforest.effects`); missing = off.

    Returns
    -------
    shift, factor, scale : dict feature -> (n,) float64
        ``x = (mu + noise * scale) * factor + shift``.
    """
    n = len(keys)
    sp = keys["species"].to_numpy()
    h = keys["height_m"].to_numpy(dtype=float)
    fp = keys["footprint_m"].to_numpy(dtype=float)
    birch = sp == "birch"
    low = ~birch
    shift = {f: np.zeros(n) for f in FEATURES}
    factor = {f: np.ones(n) for f in FEATURES}
    scale = {f: np.ones(n) for f in FEATURES}
    e = {k: float(effects.get(k, v.off)) for k, v in CATALOGUE.items()}

    u = e["understory"]  # birch: fewer peaks, lower first echo spread of E
    shift["Npeaks"] -= np.where(birch, 0.30 * u, 0.0)
    shift["H"] -= np.where(birch, 0.20 * u, 0.0)
    scale["E"] *= np.where(birch, 1.0 / (1.0 + 0.4 * u), 1.0)

    r = to_u("clumping", e["clumping"])  # strength: 0 off, 1 at the tightest radius (catalogue)
    widen = 1.0 + 3.0 * r * (_REF_FOOTPRINT_M / fp)  # low species: more heterogeneous at small footprints
    scale["H"] *= np.where(low, widen, 1.0)
    scale["Apeak"] *= np.where(low, widen, 1.0)

    s = e["xy_error"]  # birch: echoes further from the trunk, lower and more spread
    shift["H"] -= np.where(birch, 3.0 * s, 0.0)
    scale["H"] *= np.where(birch, 1.0 + 3.0 * s, 1.0)
    shift["Npeaks"] += np.where(birch, 1.2 * s, 0.0)

    q = e["specular"]  # planophile leaves of the low species flash towards the sensor
    shift["Apeak"] += np.where(low, 50.0, 10.0) * q
    shift["E"] += np.where(low, 100.0, 20.0) * q

    k = e["hotspot"] - 1.0  # first-order boost: higher, narrower echoes
    factor["Apeak"] *= 1.0 + 0.8 * k
    factor["E"] *= 1.0 + 0.3 * k
    shift["FWHM"] -= 0.8 * k

    t = e["lad_shift"]  # steeper leaves: weaker echoes from deeper in the canopy
    factor["Apeak"] *= 1.0 - 0.012 * t
    factor["E"] *= 1.0 - 0.010 * t
    shift["H"] += 0.006 * t * h

    a = e["leaf_albedo"]
    factor["Apeak"] *= a
    factor["E"] *= a**1.5

    rho = e["noise_autocorr"]  # coloured noise: spurious peaks, erratic widths
    shift["Npeaks"] += 0.6 * rho**2
    scale["FWHM"] *= 1.0 + rho**2

    f = e["trigger_loss"]  # energy lost before the trigger: later, weaker first echoes
    shift["H"] -= 2.0 * f * h / 3.0
    factor["Apeak"] *= 1.0 - 0.5 * f
    factor["E"] *= 1.0 - f
    return shift, factor, scale


def _saturate(apeak: np.ndarray, level: float) -> np.ndarray:
    """The sensor's saturation v -> L tanh(v / L) (``nonlinearity``; 0 = linear)."""
    return apeak if level <= 0 else level * np.tanh(apeak / level)


@dataclass
class SyntheticStudy:
    """Field samples, pulses and a simulator of the toy model.

    Parameters
    ----------
    samples_per_species : int
        Field samples per species and year.
    pulses_per_sample : int
        Pulses per sample and dataset.
    seed : int
        Seed of the layout (heights) and of the real data.
    perturb : dict
        Feature -> mean shift, in units of that feature's pulse SD, added to the real data
        only: a disagreement that no effect produces.
    datasets, species : dict
        Defaults :data:`DATASETS`, :data:`SPECIES`.
    """

    samples_per_species: int = 12
    pulses_per_sample: int = 8
    seed: int = 0
    perturb: dict = field(default_factory=dict)
    datasets: dict = field(default_factory=lambda: dict(DATASETS))
    species: dict = field(default_factory=lambda: dict(SPECIES))

    def __post_init__(self) -> None:
        rng = np.random.default_rng([self.seed, 1])
        rows = []
        years = sorted({d["year"] for d in self.datasets.values()})
        for sp, par in self.species.items():
            for year in years:
                for i in range(self.samples_per_species):
                    rows.append({"sample_id": f"{year}_{sp}_{i:03d}", "species": sp, "year": year,
                                 "height_m": rng.uniform(*par["h"])})
        self.samples = pd.DataFrame(rows)
        pulses = []
        for ds, dpar in self.datasets.items():
            s = self.samples[self.samples["year"] == dpar["year"]]
            m = len(s) * self.pulses_per_sample
            pulses.append(pd.DataFrame({
                "dataset": ds,
                "sample_id": np.repeat(s["sample_id"].to_numpy(), self.pulses_per_sample),
                "species": np.repeat(s["species"].to_numpy(), self.pulses_per_sample),
                "height_m": np.repeat(s["height_m"].to_numpy(), self.pulses_per_sample),
                "footprint_m": dpar["footprint_m"],
                "pulse_id": np.arange(m, dtype=np.int64),
            }))
        self.keys = pd.concat(pulses, ignore_index=True)

    def _features(self, keys: pd.DataFrame, effects: dict, z_plant: dict, z_pulse: dict) -> pd.DataFrame:
        shift, factor, scale = apply_effects(keys, effects)
        names = list(self.species)
        sp = pd.Index(names).get_indexer(keys["species"])
        h = keys["height_m"].to_numpy(dtype=float)
        cols = {c: keys[c].to_numpy() for c in ("dataset", "pulse_id", "sample_id", "species")}
        for f in FEATURES:
            par = [self.species[n][f] for n in names]
            slope = np.array([float(p[0][:-1]) if isinstance(p[0], str) else 0.0 for p in par])
            level = np.array([0.0 if isinstance(p[0], str) else p[0] for p in par])
            mu = level[sp] + slope[sp] * h
            noise = np.array([p[1] for p in par])[sp] * z_plant[f] + np.array([p[2] for p in par])[sp] * z_pulse[f]
            cols[f] = (mu + noise * scale[f]) * factor[f] + shift[f]
        cols["Apeak"] = _saturate(cols["Apeak"], float(effects.get("nonlinearity", 0.0)))
        cols["source"] = np.full(len(keys), "sim")
        return pd.DataFrame(cols)

    def real(self, effects: dict[str, float] | None = None) -> pd.DataFrame:
        """The "measured" feature table: the toy model with ``effects`` hidden in it.

        One plant draw per field sample, shared by all its pulses in every dataset.
        """
        effects = dict(effects or {})
        rng = np.random.default_rng([self.seed, 2])
        j = self.samples.set_index("sample_id").index.get_indexer(self.keys["sample_id"])
        z_plant = {f: rng.standard_normal(len(self.samples))[j] for f in FEATURES}
        z_pulse = {f: rng.standard_normal(len(self.keys)) for f in FEATURES}
        out = self._features(self.keys, effects, z_plant, z_pulse)
        for f, k in self.perturb.items():
            pulse_sd = np.array([self.species[s][f][2] for s in out["species"]])
            out[f] = out[f] + k * pulse_sd
        out["source"] = "real"
        return out

    def simulate(self, keys: pd.DataFrame, effects: dict[str, float], seed: int) -> pd.DataFrame:
        """The simulator of :mod:`.search`: features of ``keys``' pulses under ``effects``.

        Parameters
        ----------
        keys : DataFrame
            Pulses to simulate (rows of :attr:`keys`; optional column ``replicate``).
        effects : dict
            Effect name -> value.
        seed : int
            Seed; each pulse's draws depend only on (seed, dataset, pulse_id, replicate).
        """
        rep = keys["replicate"].to_numpy() if "replicate" in keys else np.zeros(len(keys), dtype=np.int64)
        ds_code = pd.Categorical(keys["dataset"], categories=sorted(self.datasets)).codes.astype(np.uint64)
        # one independent stream per pulse: a counter-based hash of its identity
        with np.errstate(over="ignore"):
            ident = (np.uint64(seed % 2**64) * np.uint64(0x9E3779B97F4A7C15)
                     ^ (ds_code << np.uint64(48))
                     ^ (keys["pulse_id"].to_numpy().astype(np.uint64) << np.uint64(8))
                     ^ rep.astype(np.uint64))
        z = _normals(ident, 2 * len(FEATURES))
        z_plant = {f: z[:, i] for i, f in enumerate(FEATURES)}
        z_pulse = {f: z[:, len(FEATURES) + i] for i, f in enumerate(FEATURES)}
        return self._features(keys.reset_index(drop=True), effects, z_plant, z_pulse)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser: a bijective, well-mixed 64-bit hash (vectorised)."""
    with np.errstate(over="ignore"):
        x = (x + np.uint64(0x9E3779B97F4A7C15)).astype(np.uint64)
        x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return x ^ (x >> np.uint64(31))


def _normals(ident: np.ndarray, k: int) -> np.ndarray:
    """(n, k) standard normals, a deterministic function of each pulse's identity."""
    from scipy.special import ndtri

    cols = []
    for i in range(k):
        bits = _splitmix64(ident ^ np.uint64((i + 1) * 0x632BE59BD9B4E019 % 2**64))
        u = ((bits >> np.uint64(11)).astype(np.float64) + 0.5) / 2.0**53
        cols.append(ndtri(u))
    return np.stack(cols, axis=1)
