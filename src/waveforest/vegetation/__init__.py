"""Geometric-optical vegetation models (docs/method.md §(g)): scenes of triangles for the MCRT engine.

``build_scene(species, height, seed, **params)`` gives a :class:`~waveforest.scene.Scene` of
a 6 x 6 m plot: one tree at the origin (birch and the other trees), a plot of shoots
(raspberry, fireweed, bracken), grass tufts, a dwarf-shrub layer, a moss/lichen carpet or a
bare surface, over a Lambertian ground plane. ``species_table()`` lists the 29 species/groups
of the paper's Table 1 with their slugs and models. All numbers live in
``resources/vegetation/`` with their sources.

Modules: :mod:`.params` (parameter files), :mod:`.lad` (leaf angle distributions),
:mod:`.leaves` (outlines, leaf placement), :mod:`.wood` (prisms), :mod:`.placement`
(uniform / Thomas positions), :mod:`.ground` (plane, micro-relief), :mod:`.tree`,
:mod:`.herbs`, :mod:`.generic` (the models), :mod:`.build` (the spec -> scene entry point),
:mod:`.gaps` (LAI, nadir gap fraction), :mod:`.render` (PNG), :mod:`.cli` (the command).
"""

from waveforest.vegetation.build import Built, VegetationError, build, build_scene
from waveforest.vegetation.gaps import leaf_area_index, nadir_coverage, nadir_gap_fraction
from waveforest.vegetation.lad import LAD_NAMES, LeafAngleDistribution, lad_by_name, sample_normals
from waveforest.vegetation.params import PLOT_AREA_M2, UnknownSpeciesError, slugs, species_params, species_table
from waveforest.vegetation.tree import allometric_leaf_area

__all__ = [
    "Built",
    "LAD_NAMES",
    "LeafAngleDistribution",
    "PLOT_AREA_M2",
    "UnknownSpeciesError",
    "VegetationError",
    "allometric_leaf_area",
    "build",
    "build_scene",
    "lad_by_name",
    "leaf_area_index",
    "nadir_coverage",
    "nadir_gap_fraction",
    "sample_normals",
    "slugs",
    "species_params",
    "species_table",
]
