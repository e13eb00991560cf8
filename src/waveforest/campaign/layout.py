"""Where things are: the study area, stands, field samples and reference targets.

The virtual study area is a rectangle (``layout.yaml`` ``area``) whose long axis points along
the main flight azimuth (160 deg); positions are handled in that frame (``s`` along track,
``w`` across track, m) and written in projected world coordinates (x east, y north).

Isolation (why one 6 x 6 m scene per sample is the whole world of its pulses): samples sit
on a grid of ``sample_spacing_m`` (12 m) nodes, jittered by at most ``sample_jitter_m``
(1 m), so two samples are at least 10 m apart. A pulse is generated only within
``radius_m + disc_margin_m`` (<= 1.7 m) of a sample; its receiver sees a 5-m circle
around the beam (docs/method.md §(d)), at most 4.2 m from the sample; the beam crosses at most
5 m * tan(15 deg) = 1.3 m horizontally over a 5-m tree. Everything a pulse can see therefore
lies within the sample's own 6 x 6 m scene or on open ground beyond it (the scene's ground),
never on a neighbouring sample (>= 10 - 3 = 7 m away). Stands are at least
``min_separation_m`` apart, and the sample grids of two stands at least one grid spacing apart
along s or w, so that samples of different stands keep those 10 m however many samples a stand
holds. Targets keep ``targets.min_separation_m`` from stand centres and from each other, and
enough distance from every sample that no sample's pulse sees a target square and no target's
pulse sees a plant (:data:`SAMPLE_PULSE_REACH_M`, :data:`TARGET_PULSE_REACH_M`,
:data:`PLANT_REACH_M`).

The layout is drawn for every campaign year (2010, 2012) whatever datasets are generated,
so a sample's position does not depend on the dataset selection; only the years of the
generated datasets are written.

Field-sample rules (docs/method.md §(a)): species of Table 1 per year (P10/S10 -> 2010, S12 -> 2012),
Table 1's design counts each (P10 + S10 in 2010, S12 in 2012; or ``samples_per_species`` each); heights uniform in the species' [min_h, max_h] of Table 1 (the comparison takes birches of 2.5-5 m,
the comparison range of docs/method.md §(i1)); radius 0.5 m (2010) / 1.0 m (2012); trees carry
``is_tree = 1``; 2010 trees belong to the P10 plots with Table 1's share P10 / (P10 + S10).
Coordinates are "GNSS" values written to mm; they are the true positions of the plants.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from waveforest.campaign.params import CampaignParamsError, load_design_counts, load_layout, load_targets
from waveforest.rng import stream_generator

YEARS = (2010, 2012)
"""Campaign years (docs/method.md §(a))."""

DESIGN_YEAR = {"P10": 2010, "S10": 2010, "S12": 2012}
"""Field designs of Table 1 and their year."""

SAMPLE_PULSE_REACH_M = 5.5
"""How far from its sample a sample's pulse sees: 1.7 m (disc) + 2.5 m (receiver) + 1.3 m (beam
crossing a 5-m tree), module docstring."""

TARGET_PULSE_REACH_M = 4.5
"""How far beyond a target's pulse disc (``radius_m``) its pulses see: <= 0.7 m disc margin +
2.5 m receiver radius + 1.3 m beam crossing."""

PLANT_REACH_M = 3.0 * np.sqrt(2.0)
"""Half-diagonal of a sample's 6 x 6 m scene (how far its plant reaches from the sample), m."""

MAX_PLACEMENT_TRIES = 20000
"""Rejection-sampling attempts when placing stands and targets with a minimum separation."""

FIELD_COLUMNS = ["sample_id", "year", "stand_id", "design", "species", "functional_group", "x", "y",
                 "ground_z", "height_m", "radius_m", "is_tree", "canopy_cover_pct"]
"""Columns of ``fields.csv`` (the user-facing schema)."""

TARGET_COLUMNS = ["target_id", "year", "material", "hdrf", "calibration", "agc", "x", "y", "z", "radius_m"]
"""Columns of ``targets.csv`` (the user-facing schema)."""


@dataclass(frozen=True)
class Frame:
    """The area frame: ``s`` along the flight azimuth, ``w`` to its right, metres from the origin."""

    origin_x: float
    origin_y: float
    azimuth_deg: float

    @property
    def u(self) -> np.ndarray:
        """(2,) unit vector along track (east, north)."""
        a = np.radians(self.azimuth_deg)
        return np.array([np.sin(a), np.cos(a)])

    @property
    def v(self) -> np.ndarray:
        """(2,) unit vector across track, to the right of ``u`` (east, north)."""
        a = np.radians(self.azimuth_deg)
        return np.array([np.cos(a), -np.sin(a)])

    def to_world(self, s, w) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) of frame coordinates (s, w), m."""
        s = np.asarray(s, dtype=np.float64)
        w = np.asarray(w, dtype=np.float64)
        u, v = self.u, self.v
        return self.origin_x + s * u[0] + w * v[0], self.origin_y + s * u[1] + w * v[1]

    def to_frame(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Frame (s, w) of world coordinates (x, y), m."""
        dx = np.asarray(x, dtype=np.float64) - self.origin_x
        dy = np.asarray(y, dtype=np.float64) - self.origin_y
        u, v = self.u, self.v
        return dx * u[0] + dy * u[1], dx * v[0] + dy * v[1]


@dataclass(frozen=True)
class Layout:
    """The drawn layout.

    Attributes
    ----------
    frame : Frame
    fields : DataFrame
        :data:`FIELD_COLUMNS` plus ``s``, ``w`` (frame coordinates), ``slug_model`` is not
        needed; ``cover_estimated`` (bool: the sample gets a visual canopy-cover estimate).
    targets : DataFrame
        :data:`TARGET_COLUMNS` plus ``site``, ``true_rho``, ``side_m``, ``on_ground_rho``,
        ``s``, ``w``.
    stands : DataFrame
        stand_id, year, s, w, x, y, z_offset.
    """

    frame: Frame
    fields: pd.DataFrame
    targets: pd.DataFrame
    stands: pd.DataFrame


def area_frame(layout: dict | None = None) -> Frame:
    """The frame of the study area (``layout.yaml`` ``area``)."""
    area = (layout or load_layout())["area"]
    return Frame(float(area["origin_x"]), float(area["origin_y"]), float(area["frame_azimuth_deg"]))


def terrain_z(layout: dict, s, w) -> np.ndarray:
    """Regional terrain elevation at frame coordinates (s, w), m a.s.l."""
    t = layout["terrain"]
    return float(t["base_z"]) + float(t["slope_along"]) * np.asarray(s) + float(t["slope_across"]) * np.asarray(w)


def _place(rng, n, half_s, half_w, min_sep, fixed: np.ndarray, fixed_sep: float, what: str,
           clear=None, hint: str = "enlarge the area or lower the separation") -> np.ndarray:
    """n points uniform in [-half_s, half_s] x [-half_w, half_w], pairwise >= min_sep, >= fixed_sep
    from ``fixed``; ``clear(i, p, pts)``, when given, must also accept point i at p beside ``pts``."""
    pts = np.empty((0, 2))
    tries = 0
    while len(pts) < n:
        tries += 1
        if tries > MAX_PLACEMENT_TRIES:
            raise CampaignParamsError(
                f"layout.yaml: cannot place {n} {what} {min_sep} m apart in the study area; {hint}")
        p = np.array([rng.uniform(-half_s, half_s), rng.uniform(-half_w, half_w)])
        if len(pts) and np.min(np.hypot(*(pts - p).T)) < min_sep:
            continue
        if len(fixed) and np.min(np.hypot(*(fixed - p).T)) < fixed_sep:
            continue
        if clear is not None and not clear(len(pts), p, pts):
            continue
        pts = np.vstack([pts, p])
    return pts


def stand_grid(m: int, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid nodes of a stand of ``m`` samples: (s, w) offsets from its centre, m (rows along s)."""
    c = max(1, int(np.ceil(np.sqrt(m))))
    r = -(-m // c)
    j = np.arange(m)
    return (j // c - (r - 1) / 2) * spacing, (j % c - (c - 1) / 2) * spacing


def _half_extents(counts: list[int], spacing: float) -> np.ndarray:
    """(n, 2) half extents (s, w) of the node boxes of stands with ``counts`` samples, m."""
    out = np.zeros((len(counts), 2))
    for k, m in enumerate(counts):
        if m:
            gs, gw = stand_grid(m, spacing)
            out[k] = gs.max(), gw.max()
    return out


def species_for_year(species: pd.DataFrame, year: int) -> pd.DataFrame:
    """Species of ``species`` (merged with the design counts) sampled in ``year``, Table 1 order."""
    designs = [d for d, y in DESIGN_YEAR.items() if y == year]
    return species[species[designs].sum(axis=1) > 0]


def _merge_species(species: pd.DataFrame) -> pd.DataFrame:
    counts = load_design_counts()
    need = {"slug", "functional_group", "min_h", "max_h", "is_tree"}
    missing = need - set(species.columns)
    if missing:
        raise CampaignParamsError(f"species table: missing column(s) {', '.join(sorted(missing))}")
    unknown = sorted(set(counts["slug"]) - set(species["slug"]))
    if unknown:
        raise CampaignParamsError(
            f"design_counts.csv: species {', '.join(unknown)} unknown to the vegetation models")
    return counts.merge(species[list(need)], on="slug", how="left")


def sample_counts(sp: pd.DataFrame, year: int, samples_per_species: int | None) -> pd.Series:
    """Field samples per species slug in ``year``: Table 1's design counts (P10 + S10 for 2010,
    S12 for 2012) when ``samples_per_species`` is None, else that many for every species of the year."""
    ys = species_for_year(sp, year)
    if samples_per_species is not None:
        return pd.Series(int(samples_per_species), index=ys["slug"].to_numpy())
    designs = [d for d, y in DESIGN_YEAR.items() if y == year]
    return pd.Series(ys[designs].fillna(0).sum(axis=1).round().astype(int).to_numpy(), index=ys["slug"].to_numpy())


def build_layout(species: pd.DataFrame, samples_per_species: int | None, seed: int) -> Layout:
    """Draw stands, field samples and targets of both campaign years.

    Parameters
    ----------
    species : DataFrame
        One row per species with columns slug, functional_group, min_h, max_h, is_tree
        (:func:`waveforest.vegetation.species_table`).
    samples_per_species : int or None
        Field samples per species and year (config ``campaign.samples_per_species``); None =
        Table 1's design counts (:func:`sample_counts`).
    seed : int
        Master seed.

    Returns
    -------
    Layout
    """
    if samples_per_species is not None and samples_per_species < 1:
        raise CampaignParamsError("campaign.samples_per_species: expected >= 1")
    lay = load_layout()
    frame = area_frame(lay)
    rng = stream_generator(seed, "layout")  # one stream, drawn from in the order of the steps below
    sp = _merge_species(species)
    n_stands = {int(y): int(c) for y, c in lay["stands"]["count"].items()}
    centres, half = _place_stands(rng, lay, sp, samples_per_species, n_stands)
    sites = load_targets()
    tcentres = _place_targets(rng, lay, sites, centres, half)
    stands, fields = _draw_samples(rng, lay, frame, sp, samples_per_species, centres, n_stands)
    fields = _sample_attributes(rng, lay, frame, sp, fields)
    targets = _targets_table(rng, lay, frame, sites, tcentres)
    return Layout(frame=frame, fields=fields, targets=targets, stands=stands)


def _place_stands(rng, lay: dict, sp: pd.DataFrame, samples_per_species: int, n_stands: dict
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Stand centres (total, 2) in the area frame, m, and the half extents (total, 2) of their sample grids.

    Stands of both years, placed at random (:func:`_place`) at least ``stands.min_separation_m``
    apart and with the sample grids of two stands one ``sample_spacing_m`` apart or more.
    Raises CampaignParamsError when they do not fit.
    """
    area, st = lay["area"], lay["stands"]
    half_s = float(area["along_m"]) / 2 - float(st["edge_margin_m"])
    half_w = float(area["across_m"]) / 2 - float(st["edge_margin_m"])
    total = sum(n_stands[y] for y in YEARS)
    spacing = float(st["sample_spacing_m"])
    # samples per stand (the species' samples of a year dealt round-robin to its stands)
    n_year = {y: int(sample_counts(sp, y, samples_per_species).sum()) for y in YEARS}
    counts = [len(range(k, n_year[y], n_stands[y])) for y in YEARS for k in range(n_stands[y])]
    half = _half_extents(counts, spacing)

    def stands_clear(i, p, pts):
        # node boxes of two stands at least one grid spacing apart along s or w: their
        # samples keep the within-stand distance (spacing - 2 jitter) whatever the jitter
        gap = np.abs(pts - p) - half[:len(pts)] - half[i]
        return bool(np.all(np.max(gap, axis=1) >= spacing))

    centres = _place(rng, total, half_s, half_w, float(st["min_separation_m"]), np.empty((0, 2)), 0.0,
                     "stands of " + ("Table 1's design counts" if samples_per_species is None
                                     else f"{samples_per_species} samples per species and year"), stands_clear,
                     "lower campaign.samples_per_species, enlarge the area or lower the separation")
    return centres, half


def _place_targets(rng, lay: dict, sites: pd.DataFrame, centres: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Target centres (n_sites, 2) in the area frame, m: isolated from every stand (no sample's
    pulse sees a target square, no target pulse sees a plant) and ``targets.min_separation_m`` apart."""
    area, st = lay["area"], lay["stands"]
    half_s = float(area["along_m"]) / 2 - float(st["edge_margin_m"])
    half_w = float(area["across_m"]) / 2 - float(st["edge_margin_m"])
    tsep = float(lay["targets"]["min_separation_m"])
    reach = np.maximum(np.asarray(sites["side_m"], dtype=float) / np.sqrt(2.0) + SAMPLE_PULSE_REACH_M,
                       np.asarray(sites["radius_m"], dtype=float) + TARGET_PULSE_REACH_M + PLANT_REACH_M)
    reach += np.sqrt(2.0) * float(st["sample_jitter_m"])

    def target_clear(i, p, pts):
        # no sample's pulse sees the target square, no target pulse sees a plant (isolation)
        gap = np.maximum(np.abs(centres - p) - half, 0.0)
        return bool(np.min(np.hypot(gap[:, 0], gap[:, 1])) >= reach[i])

    return _place(rng, len(sites), half_s, half_w, tsep, centres, tsep, "targets", target_clear)


def _draw_samples(rng, lay: dict, frame, sp: pd.DataFrame, samples_per_species: int, centres: np.ndarray,
                  n_stands: dict) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The stands table and the field samples (year, stand_id, idx, species, s, w, ground_z).

    Per year the species' samples in random order are dealt round-robin to the year's stands;
    each stand's samples sit on its grid (:func:`stand_grid`) with uniform jitter, at the
    terrain height plus the stand's offset and a per-sample N(0, ``terrain.sample_z_sd``).
    """
    t, st = lay["terrain"], lay["stands"]
    spacing = float(st["sample_spacing_m"])
    jitter = float(st["sample_jitter_m"])
    stand_rows, field_rows = [], []
    k0 = 0
    for year in YEARS:
        counts = sample_counts(sp, year, samples_per_species)
        slugs = np.repeat(counts.index.to_numpy(), counts.to_numpy())
        order = rng.permutation(len(slugs))
        slugs = slugs[order]
        nst = n_stands[year]
        offsets = rng.normal(0.0, float(t["stand_z_sd"]), nst)
        for k in range(nst):
            cs, cw = centres[k0 + k]
            sx, sy = frame.to_world(cs, cw)
            stand_id = f"{year}-{k + 1:02d}"
            stand_rows.append({"stand_id": stand_id, "year": year, "s": cs, "w": cw, "x": float(sx),
                               "y": float(sy), "z_offset": float(offsets[k])})
            mine = slugs[k::nst]
            m = len(mine)
            if m == 0:
                continue
            gs, gw = stand_grid(m, spacing)
            gs = gs + rng.uniform(-jitter, jitter, m)
            gw = gw + rng.uniform(-jitter, jitter, m)
            zs = terrain_z(lay, cs + gs, cw + gw) + offsets[k] + rng.normal(0.0, float(t["sample_z_sd"]), m)
            for i, slug in enumerate(mine):
                field_rows.append({"year": year, "stand_id": stand_id, "idx": i, "species": slug,
                                   "s": cs + gs[i], "w": cw + gw[i], "ground_z": zs[i]})
        k0 += nst
    return pd.DataFrame(stand_rows), pd.DataFrame(field_rows)


def _sample_attributes(rng, lay: dict, frame, sp: pd.DataFrame, fields: pd.DataFrame) -> pd.DataFrame:
    """The fields.csv columns of the drawn samples (:data:`FIELD_COLUMNS` + s, w, cover_estimated).

    Height uniform in the species' [min_h, max_h] (or ``samples.height_override_m``), m,
    2 decimals; design (S12 in 2012; P10 for a tree with probability P10 / (P10 + S10), else
    S10); plot radius by year; the S12 samples whose cover is estimated (probability
    ``samples.canopy_cover_fraction``); positions rounded to ``samples.position_decimals``.
    """
    smp = lay["samples"]
    info = sp.set_index("slug")
    fields["functional_group"] = info.loc[fields["species"], "functional_group"].to_numpy()
    fields["is_tree"] = info.loc[fields["species"], "is_tree"].to_numpy().astype(bool).astype(int)
    lo = info.loc[fields["species"], "min_h"].to_numpy(dtype=float).copy()
    hi = info.loc[fields["species"], "max_h"].to_numpy(dtype=float).copy()
    for slug, (a, b) in (smp.get("height_override_m") or {}).items():
        sel = fields["species"].to_numpy() == slug
        lo[sel], hi[sel] = float(a), float(b)
    u = rng.random(len(fields))
    fields["height_m"] = np.round(lo + u * (hi - lo), 2)
    p10 = info.loc[fields["species"], "P10"].to_numpy(dtype=float)
    s10 = info.loc[fields["species"], "S10"].to_numpy(dtype=float)
    share = np.where(p10 + s10 > 0, p10 / np.maximum(p10 + s10, 1), 0.0)
    u = rng.random(len(fields))
    design = np.where(fields["year"] == 2012, "S12", np.where((fields["is_tree"] == 1) & (u < share), "P10", "S10"))
    fields["design"] = design
    fields["radius_m"] = fields["year"].map({int(k): float(v) for k, v in smp["radius_m"].items()})
    u = rng.random(len(fields))
    fields["cover_estimated"] = (fields["design"] == "S12") & (u < float(smp["canopy_cover_fraction"]))
    fields["canopy_cover_pct"] = np.nan
    dec = int(smp["position_decimals"])
    x, y = frame.to_world(fields["s"], fields["w"])
    fields["x"], fields["y"] = np.round(x, dec), np.round(y, dec)
    fields["ground_z"] = np.round(fields["ground_z"].to_numpy(dtype=float), dec)
    fields["s"], fields["w"] = frame.to_frame(fields["x"], fields["y"])
    fields["sample_id"] = [f"{sid}-{i + 1:03d}" for sid, i in zip(fields["stand_id"], fields["idx"])]
    fields = fields.drop(columns="idx")
    return fields[FIELD_COLUMNS + ["s", "w", "cover_estimated"]].reset_index(drop=True)


def _targets_table(rng, lay: dict, frame, sites: pd.DataFrame, tcentres: np.ndarray) -> pd.DataFrame:
    """targets.csv rows, one per target site and year it is laid out, with the truth columns
    (site, true_rho, side_m, on_ground_rho) and the frame coordinates s, w; z = terrain + N(0, stand_z_sd)."""
    dec = int(lay["samples"]["position_decimals"])
    zt = rng.normal(0.0, float(lay["terrain"]["stand_z_sd"]), len(sites))
    trows = []
    for i, site in sites.iterrows():
        cs, cw = tcentres[i]
        tx, ty = frame.to_world(cs, cw)
        tz = float(terrain_z(lay, cs, cw) + zt[i])
        for year in (int(v) for v in str(site["years"]).split()):
            trows.append({
                "target_id": f"{site['site']}_{year}", "year": year, "material": site["material"],
                "hdrf": site["hdrf"], "calibration": int(site["calibration"]), "agc": int(site["agc"]),
                "x": round(float(tx), dec), "y": round(float(ty), dec), "z": round(tz, dec),
                "radius_m": float(site["radius_m"]), "site": site["site"], "true_rho": float(site["true_rho"]),
                "side_m": float(site["side_m"]), "on_ground_rho": site["on_ground_rho"]})
    targets = pd.DataFrame(trows)
    targets["s"], targets["w"] = frame.to_frame(targets["x"], targets["y"])
    return targets
