"""The study report and every figure.

- :mod:`.build` -- the report of a run: every table and figure, the config and software versions;
- :mod:`.markdown` -- small Markdown table helpers;
- :mod:`.plots` -- all figures of the stages, and :func:`~.plots.pyplot` / :func:`~.plots.save_png`.
"""

from waveforest.report.build import ReportOutputs, collect, run, versions

__all__ = ["ReportOutputs", "collect", "run", "versions"]
