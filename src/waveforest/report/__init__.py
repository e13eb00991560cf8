"""The study report and every figure.

- :mod:`.build` -- the report of a run: every table and figure, the config and software versions;
- :mod:`.source` -- its opening: the data source, config changes, datasets and counts;
- :mod:`.provenance` -- the code's commit, the input files' SHA-256 and the machine;
- :mod:`.summary` -- its summary: the results beside the paper's;
- :mod:`.markdown` -- Markdown tables and the report's small Markdown-to-HTML converter;
- :mod:`.plots` -- all figures of the stages (drawn with :mod:`waveforest.plotting`).
"""

from waveforest.report.build import collect, versions

__all__ = ["collect", "versions"]
