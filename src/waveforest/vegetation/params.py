"""Parameter files of the vegetation models (``resources/vegetation/``).

Every number of the models lives in these files, each with its source (keys of
``references.csv``; ``ASSUMPTION`` where no published value was verified):

- ``table1_species.csv``: copy of the paper's Table 1 (Hovi & Korpela 2014), the reference
  list of species/groups, functional groups and field height ranges.
- ``species.csv``: one row per species: model family, foliage element (leaf outline), leaf
  angle distribution, optical properties at 1064 nm, sane height range.
- ``structure.csv``: structural numbers, one per row (slug, param, value, unit, source).
- ``outlines/*.csv``: leaf outline polygons (see :mod:`waveforest.vegetation.leaves`).

The loader checks that every model gets exactly the parameters it needs, so a typo in a
file is an error naming the file, the species and the parameter.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from waveforest import RESOURCES
from waveforest.errors import WaveforestError
from waveforest.species import slug_of

RES = RESOURCES / "vegetation"
"""Folder of the vegetation parameter files."""

PLOT_HALF_M = 3.0
"""Half side of the square scene, m: every scene covers x, y in [-3, 3] (a 6 x 6 m plot)."""

PLOT_AREA_M2 = (2 * PLOT_HALF_M) ** 2
"""Ground area of a scene, m^2 (the denominator of LAI)."""

MODELS = ("tree", "shoots", "tufts", "layer", "surface", "residue")
"""Model families (column ``model`` of species.csv)."""

PAPER_MODELS = ("birch", "raspberry", "fireweed")
"""The three species modelled by Hovi & Korpela (2014)."""

_TREE = (
    "crown_base_frac stem_base_diameter_per_h stem_top_diameter_m "
    "whorl_spacing_m branches_per_whorl whorl_divergence_deg branch_azimuth_jitter_deg "
    "branch_length_frac branch_length_cv crown_widest_depth crown_top_exponent crown_base_length_rel "
    "branch_zenith_top_deg branch_zenith_base_deg branch_bend_deg branch_diameter_base_m "
    "branch_diameter_per_length sub_spacing_m sub_length_rel sub_angle_deg shoot_start_frac "
    "leaves_per_shoot leaf_area_cm2 leaf_area_cv leaf_length_width petiole_m"
)
_SHOOTS = (
    "lai shoot_height_min_frac leafy_from nodes_per_shoot leaves_per_node divergence_deg "
    "leaflets_lower leaflets_upper compound_split lateral_rel_1 lateral_rel_2 leaf_area_cm2 "
    "size_base_rel size_peak_pos size_top_rel leaf_length_width petiole_m petiole_elev_deg "
    "lean_frac stem_base_diameter_m stem_top_diameter_m stem_segments leaflet_spread_deg "
    "plants_per_cluster"
)
_TUFTS = (
    "lai blades_per_tuft blade_width_m blade_length_min_frac blade_length_max_frac tuft_radius_m "
    "blade_reach_max_m plants_per_cluster"
)
_LAYER = (
    "lai stems_per_m2 stem_diameter_m stem_height_min_frac clump_radius_m stems_per_clump "
    "leafy_from crown_radius_m leaf_area_cm2 leaf_length_width"
)
_SURFACE = "relief_rms_m relief_corr_m grid_m carpet_min_m"
_RESIDUE = (
    _SURFACE + " wood_area_index piece_length_min_m piece_length_max_m piece_diameter_min_m "
    "piece_diameter_max_m piece_tilt_max_deg lai leaf_area_cm2 leaf_length_width"
)
REQUIRED: dict[str, tuple[str, ...]] = {
    "tree": tuple(_TREE.split()),
    "shoots": tuple(_SHOOTS.split()),
    "tufts": tuple(_TUFTS.split()),
    "layer": tuple(_LAYER.split()),
    "surface": tuple(_SURFACE.split()),
    "residue": tuple(_RESIDUE.split()),
}
"""Structural parameters (structure.csv) that each model family needs, no more, no less ..."""

TREE_LEAF_AREA: dict[str, tuple[str, ...]] = {
    "young_tree_chain": ("naslund_a", "naslund_b", "stump_d0_cm", "stump_d1", "leaf_mass_a", "leaf_mass_b",
                         "sla_m2_per_kg"),
    "power_law": ("foliage_area_a", "foliage_area_b"),
}
"""... plus, for a tree, exactly one of these groups: its total leaf area allometry
(:func:`waveforest.vegetation.tree.allometric_leaf_area`)."""

_NEEDS_LEAVES = {"tree", "shoots", "tufts", "layer", "residue"}
_NEEDS_WOOD = {"tree", "shoots", "layer", "residue"}
_NEEDS_SURFACE = {"surface", "residue"}


class ParameterFileError(WaveforestError):
    """A vegetation parameter file that is missing, malformed or inconsistent."""


class UnknownSpeciesError(WaveforestError):
    """A species slug that the parameter tables do not know."""


@dataclass(frozen=True)
class SpeciesParams:
    """Everything the model of one species needs.

    Attributes
    ----------
    slug, name, model, element, lad : str
        Identifier, Table 1 name, model family, foliage element (outline name, '' for
        surfaces) and leaf angle distribution name ('' for surfaces).
    leaf_rho, leaf_tau, wood_rho, wood_tau, surface_rho : float
        Bi-Lambertian optical properties at 1064 nm (NaN where the model has no such part).
    surface_kind : int
        Element kind of a surface model (0 ground, 3 other); -1 if none.
    h_min_ok, h_max_ok : float
        Accepted height range of :func:`~waveforest.vegetation.build_scene`, m.
    structure : dict[str, float]
        Structural numbers of structure.csv for this species.
    """

    slug: str
    name: str
    model: str
    element: str
    lad: str
    leaf_rho: float
    leaf_tau: float
    wood_rho: float
    wood_tau: float
    surface_rho: float
    surface_kind: int
    h_min_ok: float
    h_max_ok: float
    structure: dict = field(default_factory=dict)

    def __getitem__(self, name: str) -> float:
        try:
            return self.structure[name]
        except KeyError:
            raise ParameterFileError(
                f"{RES / 'structure.csv'}: species {self.slug!r} has no parameter {name!r}"
            ) from None


def _read_csv(path: Path) -> pd.DataFrame:
    if not path.exists():
        raise ParameterFileError(f"{path}: parameter file missing")
    try:
        return pd.read_csv(path, comment="#", skipinitialspace=True)
    except Exception as exc:  # pandas raises several parser errors
        raise ParameterFileError(f"{path}: not a readable CSV ({exc})") from exc


def _check_files(t1: pd.DataFrame, sp: pd.DataFrame, st: pd.DataFrame) -> list[str]:
    """Check the columns of species.csv and structure.csv, species.csv against Table 1 (same
    names, same order, slugs of :func:`waveforest.species.slug_of`) and that every structure
    number has a source and appears once; return the slugs in Table 1 order.

    Raises :class:`ParameterFileError` naming the file."""
    path_sp, path_st = RES / "species.csv", RES / "structure.csv"
    for col in ("slug", "name", "model", "element", "lad", "leaf_rho", "leaf_tau", "wood_rho",
                "wood_tau", "surface_rho", "surface_kind", "h_min_ok", "h_max_ok", "optics_source"):
        if col not in sp.columns:
            raise ParameterFileError(f"{path_sp}: column {col!r} missing")
    for col in ("slug", "param", "value", "unit", "source"):
        if col not in st.columns:
            raise ParameterFileError(f"{path_st}: column {col!r} missing")
    if list(sp["name"]) != list(t1["species"]):
        raise ParameterFileError(f"{path_sp}: names must list table1_species.csv in order")
    slugs = [slug_of(n) for n in t1["species"]]
    if list(sp["slug"]) != slugs:
        raise ParameterFileError(f"{path_sp}: slugs must be {slugs}")
    if st["source"].isna().any():
        bad = st.loc[st["source"].isna(), ["slug", "param"]].values.tolist()
        raise ParameterFileError(f"{path_st}: every number needs a source; missing for {bad}")
    dup = st.duplicated(["slug", "param"])
    if dup.any():
        raise ParameterFileError(f"{path_st}: duplicate rows {st.loc[dup, ['slug', 'param']].values.tolist()}")
    return slugs


def _structure(row, st: pd.DataFrame) -> dict[str, float]:
    """The structural numbers of species ``row`` (a species.csv row): exactly the parameters
    its model family needs (:data:`REQUIRED`; trees plus one :data:`TREE_LEAF_AREA` group),
    all finite; else :class:`ParameterFileError`."""
    path_sp, path_st = RES / "species.csv", RES / "structure.csv"
    if row.model not in MODELS:
        raise ParameterFileError(f"{path_sp}: {row.slug}: model {row.model!r} not one of {MODELS}")
    rows = st[st["slug"] == row.slug]
    got = set(rows["param"])
    need = set(REQUIRED[row.model])
    if row.model == "tree":  # plus the one leaf-area group the row gives
        need |= next((set(g) for g in TREE_LEAF_AREA.values() if set(g) <= got), set(TREE_LEAF_AREA["power_law"]))
    if got != need:
        raise ParameterFileError(
            f"{path_st}: {row.slug} ({row.model}): missing {sorted(need - got)}, "
            f"unexpected {sorted(got - need)}"
        )
    values = pd.to_numeric(rows["value"], errors="coerce").to_numpy(dtype=float)
    if not np.all(np.isfinite(values)):
        raise ParameterFileError(f"{path_st}: {row.slug}: non-numeric value")
    return dict(zip(rows["param"], values.tolist()))


def _species_params(row, st: pd.DataFrame) -> SpeciesParams:
    """The parameters of species ``row`` (a species.csv row); optical properties the model
    needs must lie in [0, 1] with ``leaf_rho + leaf_tau <= 1``, leaf models need an element
    and a LAD, surface models a ``surface_kind`` of 0 or 3; else :class:`ParameterFileError`."""
    path_sp = RES / "species.csv"
    structure = _structure(row, st)

    def num(col: str, needed: bool) -> float:
        v = getattr(row, col)
        v = float(v) if pd.notna(v) else float("nan")
        if needed and not (np.isfinite(v) and 0.0 <= v <= 1.0):
            raise ParameterFileError(f"{path_sp}: {row.slug}: {col} must be in [0, 1], got {v}")
        return v

    leaf = row.model in _NEEDS_LEAVES
    p = SpeciesParams(
        slug=row.slug,
        name=row.name,
        model=row.model,
        element=str(row.element) if pd.notna(row.element) else "",
        lad=str(row.lad) if pd.notna(row.lad) else "",
        leaf_rho=num("leaf_rho", leaf),
        leaf_tau=num("leaf_tau", leaf),
        wood_rho=num("wood_rho", row.model in _NEEDS_WOOD),
        wood_tau=num("wood_tau", row.model in _NEEDS_WOOD),
        surface_rho=num("surface_rho", row.model in _NEEDS_SURFACE),
        surface_kind=int(row.surface_kind) if pd.notna(row.surface_kind) else -1,
        h_min_ok=float(row.h_min_ok),
        h_max_ok=float(row.h_max_ok),
        structure=structure,
    )
    if leaf and (not p.element or not p.lad):
        raise ParameterFileError(f"{path_sp}: {row.slug}: a {row.model} model needs element and lad")
    if leaf and p.leaf_rho + p.leaf_tau > 1.0:
        raise ParameterFileError(f"{path_sp}: {row.slug}: leaf_rho + leaf_tau > 1")
    if row.model in _NEEDS_SURFACE and p.surface_kind not in (0, 3):
        raise ParameterFileError(f"{path_sp}: {row.slug}: surface_kind must be 0 or 3")
    return p


@functools.lru_cache(maxsize=1)
def _tables() -> tuple[pd.DataFrame, dict[str, SpeciesParams]]:
    """The species table (:func:`species_table`) and the parameters by slug, read and
    checked once."""
    t1 = _read_csv(RES / "table1_species.csv")
    sp = _read_csv(RES / "species.csv")
    st = _read_csv(RES / "structure.csv")
    slugs = _check_files(t1, sp, st)
    params = {row.slug: _species_params(row, st) for row in sp.itertuples(index=False)}
    table = pd.DataFrame(
        {
            "slug": slugs,
            "name": t1["species"].astype(str),
            "scientific_name": t1["scientific_name"].fillna("").astype(str),
            "functional_group": t1["functional_group"].astype(str),
            "model": sp["model"].astype(str),
            "min_h": t1["min_h"].astype(float),
            "max_h": t1["max_h"].astype(float),
            "is_tree": t1["functional_group"].isin(["conifer", "broadleaf"]).to_numpy(),
            "reference_surface": t1["reference_surface"].astype(bool).to_numpy(),
            "paper_model": [s in PAPER_MODELS for s in slugs],
        }
    )
    return table, params


def species_table() -> pd.DataFrame:
    """One row per species/group of the paper's Table 1 (29 rows).

    Returns
    -------
    pandas.DataFrame
        Columns ``slug``, ``name`` (as in Table 1), ``scientific_name``,
        ``functional_group`` (conifer | broadleaf | low_green | low_barren_abiotic),
        ``model`` (tree | shoots | tufts | layer | surface | residue), ``min_h``, ``max_h``
        (field height range of Table 1, m), ``is_tree``, ``reference_surface`` and
        ``paper_model`` (birch, raspberry, fireweed: the models of Hovi & Korpela 2014).
    """
    return _tables()[0].copy()


def slugs() -> list[str]:
    """Every species slug, in Table 1 order."""
    return list(_tables()[0]["slug"])


def species_params(slug: str) -> SpeciesParams:
    """The parameters of species ``slug``; an unknown slug is an error listing the valid ones."""
    params = _tables()[1]
    if slug not in params:
        raise UnknownSpeciesError(
            f"species {slug!r}: unknown; expected one of {', '.join(params)}"
        )
    return params[slug]
