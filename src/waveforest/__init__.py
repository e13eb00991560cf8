"""waveforest: simulate and analyse waveform-recording airborne LiDAR over vegetation.

After Hovi & Korpela (2014), Remote Sensing of Environment 140, 665-678.
"""

from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

try:
    __version__ = version("waveforest")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

RESOURCES = Path(__file__).parent / "resources"
"""Folder of parameter files, leaf outlines and reference tables (``resources/`` in the repo)."""
