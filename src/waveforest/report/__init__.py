"""The study report and every figure.

- :mod:`.build` -- the report of a run: every table and figure, the config and software versions;
- :mod:`.markdown` -- small Markdown table helpers;
- :mod:`.plots` -- all figures of the stages (drawn with :mod:`waveforest.plotting`).
"""

from waveforest.report.build import collect, versions

__all__ = ["collect", "versions"]
