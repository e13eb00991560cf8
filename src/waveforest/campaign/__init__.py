"""The virtual ALS60 campaign: the embedded default data, with hidden effects (docs/design.md).

``waveforest synthesize`` (:mod:`waveforest.stages.synthesize`) writes a campaign folder in
the layout a user provides for real data (``datasets.csv``, ``fields.csv``, ``targets.csv``,
LAS 1.4 waveform files, trajectory CSVs; schema in :mod:`.readme`) plus ``truth.json``, which
no analysis step reads. Seeded streams come from :mod:`waveforest.rng` (keyed streams).

Modules:

- :mod:`.params` -- the parameter files in ``resources/campaign``;
- :mod:`.layout` -- stands, field samples and targets;
- :mod:`.flight` -- strips, scan pattern, trajectories, pulses near the sites;
- :mod:`.scenes` -- the true scene of each site;
- :mod:`.site_trace` -- every site's pulses traced on its scene, sites in parallel threads;
- :mod:`.system_pulse` -- the true S(t);
- :mod:`.agc_loop` -- the true AGC;
- :mod:`.dr_cfd` -- the sensor's DR discriminator;
- :mod:`.truth_sensor` -- the sensor as it really behaves;
- :mod:`.synthesize` -- the orchestration (:func:`run`);
- :mod:`.readme` -- the campaign folder's README.
"""

from waveforest.campaign.agc_loop import AGCParams, agc_sequence
from waveforest.campaign.layout import Frame, Layout, build_layout
from waveforest.campaign.params import load_datasets, load_layout, load_targets
from waveforest.campaign.synthesize import CampaignSettings, CampaignSummary, resolve_effects, run
from waveforest.campaign.system_pulse import TrueSystemWaveform, true_system_waveform
from waveforest.campaign.truth_sensor import TruthSensor, record

__all__ = [
    "AGCParams", "agc_sequence", "Frame", "Layout", "build_layout", "load_datasets", "load_layout",
    "load_targets", "CampaignSettings", "CampaignSummary", "resolve_effects", "run", "TrueSystemWaveform",
    "true_system_waveform", "TruthSensor", "record",
]
