"""gap.png: one panel without candidates, two with; gap intervals drawn at or above 0."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from matplotlib.container import ErrorbarContainer
from test_diagnose_gap import clustered

from waveforest.diagnose import before_after as BA
from waveforest.diagnose.figures import draw_gap_figure, gap_figure
from waveforest.plotting import pyplot


@pytest.fixture(scope="module")
def gap_table() -> pd.DataFrame:
    rng = np.random.default_rng(3)
    real, sim = clustered(rng, samples=6), clustered(rng, samples=6)
    t = BA.before_after(real, sim, sim, n_boot=50, seed=4, wasserstein=False)
    t.loc[t["level"] == "total", ["before_ci_low", "after_ci_low"]] = -0.03  # as an unclipped table had
    return t


def _candidates(n: int) -> pd.DataFrame:
    return pd.DataFrame({"round": [1] * n, "rank": list(range(1, n + 1)), "name": [f"e{i}" for i in range(n)],
                         "gap_reduction": [0.1] * n, "reduction_ci_low": [-0.05] * n,
                         "reduction_ci_high": [0.2] * n, "named": [i == 0 for i in range(n)]})


@pytest.mark.parametrize("n_candidates, n_axes", [(0, 1), (2, 2)])
def test_gap_figure_has_the_candidates_panel_only_when_candidates_were_tested(gap_table, n_candidates, n_axes,
                                                                             tmp_path):
    fig = draw_gap_figure(gap_table, _candidates(n_candidates), title="verdict: none")
    try:
        assert len(fig.axes) == n_axes
        bars = [c for c in fig.axes[0].containers if isinstance(c, ErrorbarContainer)]
        assert len(bars) == 2  # before and after
        for c in bars:  # the gaps' error bars: never below 0
            assert min(seg[:, 1].min() for seg in c.lines[2][0].get_segments()) >= 0
    finally:
        pyplot().close(fig)
    path = gap_figure(gap_table, _candidates(n_candidates), tmp_path / "gap.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
