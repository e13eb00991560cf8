"""Diagnosis: where simulation and measurement disagree, which missing effect explains it.

Beyond Hovi & Korpela (2014): the authors listed candidate reasons for the gaps between
their simulated and real waveform features (docs/method.md §(j)) but could not test them. This
package does it as a workflow stage (``waveforest diagnose``):

* :mod:`.gap` — the documented measure of disagreement per dataset x species x feature,
  one total, a noise floor and cluster-bootstrap confidence intervals;
* :mod:`.catalogue` — the effects of :mod:`waveforest.effects` as one-parameter
  components of the simulation model (search scale, grid, where each acts);
* :mod:`.search` — fit each candidate on one half of the field samples with common random
  numbers, test it on the other half, name the best significant one, repeat;
* :mod:`.model` — ``model.yaml`` (the extended model) writing and reading;
* :mod:`.synthetic` — a cheap simulator with known effect signatures (tests, demos);
* :mod:`.simulator` — the adapter to the study's real ``simulate`` stage;
* :mod:`.run` / :mod:`.cli` — orchestration and the ``diagnose`` command.
"""

from waveforest.diagnose.gap import (
    FEATURE_SD_FLOOR,
    FEATURES,
    GapData,
    GapReport,
    gap_report,
    paired_reduction,
    total_gap,
)

__all__ = [
    "FEATURES",
    "FEATURE_SD_FLOOR",
    "GapData",
    "GapReport",
    "gap_report",
    "paired_reduction",
    "total_gap",
]
