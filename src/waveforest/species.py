"""The species and groups of the paper's Table 1, by slug: the names every module agrees on.

A base module (it imports only the package root for the resources folder): the config
checker (:mod:`waveforest.config`), the campaign table readers (:mod:`waveforest.io.tables`)
and the vegetation parameter loader (:mod:`waveforest.vegetation.params`) take the list of
known species from here. The list is ``resources/vegetation/table1_species.csv`` (column
``species``), each name turned into a slug by :func:`slug_of`.
"""

from __future__ import annotations

import csv
import functools

from waveforest import RESOURCES

TABLE1_CSV = RESOURCES / "vegetation" / "table1_species.csv"
"""Copy of the paper's Table 1 (Hovi & Korpela 2014): one row per species/group."""

_SPECIAL_SLUGS = {"Birches": "birch", "American red raspberry": "raspberry"}


def slug_of(name: str) -> str:
    """Snake-case slug of a Table 1 name (``"Scots pine"`` -> ``"scots_pine"``).

    Two names have short slugs: ``"Birches"`` -> ``"birch"`` and ``"American red raspberry"``
    -> ``"raspberry"``. Otherwise ``'s`` becomes ``s``, every other non-alphanumeric character
    a separator, and the lower-cased words are joined by ``_``.
    """
    if name in _SPECIAL_SLUGS:
        return _SPECIAL_SLUGS[name]
    s = "".join(c.lower() if c.isalnum() else " " for c in name.replace("'s", "s"))
    return "_".join(s.split())


@functools.cache
def _species_slugs() -> tuple[str, ...]:
    with open(TABLE1_CSV, newline="") as fh:
        return tuple(slug_of(row["species"]) for row in csv.DictReader(fh, skipinitialspace=True))


def species_slugs() -> list[str]:
    """Every species slug of Table 1, in the table's order (29 slugs).

    Raises
    ------
    OSError
        If ``table1_species.csv`` cannot be read.
    KeyError
        If it has no ``species`` column.
    """
    return list(_species_slugs())
