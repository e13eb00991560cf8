"""Simulated echo widths against the paper's simulated column of Table 3 (issue 7).

Each species at each Table 3 dataset's footprint, pulse width, sampling and range
(``benchmarks/paper_fwhm.py``): the mean first-echo FWHM within 10 % of Hovi & Korpela's
simulated mean (their own simulations matched their real data "all within 11 %"). Measured
(seed 5, 240 pulses, 4000 rays): birch -8.4 ... +4.2 %, raspberry -7.9 ... -5.3 %, fireweed
+2.3 ... +6.1 %.
"""

import importlib.util
from pathlib import Path

import pytest

from waveforest.io.paper import table3

_spec = importlib.util.spec_from_file_location(
    "paper_fwhm", Path(__file__).resolve().parents[1] / "benchmarks" / "paper_fwhm.py")
paper_fwhm = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(paper_fwhm)

TOLERANCE = 0.10


@pytest.mark.slow
@pytest.mark.parametrize("species", ["birch", "raspberry", "fireweed"])
def test_simulated_fwhm_agrees_with_the_papers_simulations(species):
    paper = table3().set_index(["dataset", "species", "feature"])["sim_mean"]
    got = {ds: paper_fwhm.measure(species, ds)["FWHM"] for ds in paper_fwhm.DATASETS}
    dev = {ds: got[ds] / paper[ds, species, "FWHM"] - 1.0 for ds in got}
    assert all(abs(d) <= TOLERANCE for d in dev.values()), {ds: f"{100 * d:+.1f} %" for ds, d in dev.items()}
    # the paper's birch echoes widen with the footprint at a given pulse width (2012: 0.15 -> 0.42 m)
    if species == "birch":
        assert got["2012_10_1"] < got["2012_20_1"] < got["2012_27_1"]
