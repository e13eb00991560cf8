"""The study report: every table and figure of a run, the config and software versions."""

from waveforest.report.build import ReportOutputs, collect, run, versions

__all__ = ["ReportOutputs", "collect", "run", "versions"]
