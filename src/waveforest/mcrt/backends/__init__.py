"""Ray-triangle intersectors behind one interface (:class:`.base.Intersector`).

- ``embree``: Embree 4 called from Numba kernels (:mod:`.embree`); embreex's ``run`` where
  libembree4 cannot be called directly.
- ``embreex``: always embreex's ``run`` (:mod:`.embreex`).
- ``numpy``: the brute-force float64 reference (:mod:`.numpy`), for small tests.
"""

from __future__ import annotations

from waveforest.mcrt.backends import embree
from waveforest.mcrt.backends.base import Intersector
from waveforest.mcrt.backends.embree import DirectEmbreeIntersector
from waveforest.mcrt.backends.embreex import EmbreeIntersector
from waveforest.mcrt.backends.numpy import NumpyIntersector


def _embree(triangles, quality: str) -> Intersector:
    if embree.available():
        return DirectEmbreeIntersector(triangles, quality)
    return EmbreeIntersector(triangles)


BACKENDS = {
    "embree": _embree,
    "embreex": lambda triangles, quality: EmbreeIntersector(triangles),
    "numpy": lambda triangles, quality: NumpyIntersector(triangles),
}
"""Intersector factories ``(triangles, quality) -> Intersector`` by backend name."""

__all__ = ["BACKENDS", "DirectEmbreeIntersector", "EmbreeIntersector", "Intersector", "NumpyIntersector"]
