"""Fly your own survey: a user's scene and flight -> LAS 1.4 waveform files (docs/survey.md).

Modules: :mod:`.spec` (SURVEY.yaml, SCENE.yaml and their closed schemas), :mod:`.scene`
(meshes, OBJ + MTL, plants as prototype instances, ground), :mod:`.scan` (legs, trajectory,
scan patterns), :mod:`.engine` (tiles: trace with multiple scattering, sensor twin, pulse
tables), :mod:`.run` (resumable tiles, parts for jobs, the merge into DIR).
"""

from waveforest.survey.engine import sensor_setup, survey_mcrt
from waveforest.survey.run import merge, run_survey, run_tiles
from waveforest.survey.scene import SurveyScene, load_scene
from waveforest.survey.spec import Survey, SurveyError, als60, load_survey

__all__ = ["Survey", "SurveyError", "SurveyScene", "als60", "load_scene", "load_survey", "merge", "run_survey",
           "run_tiles", "sensor_setup", "survey_mcrt"]
