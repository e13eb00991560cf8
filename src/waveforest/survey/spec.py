"""SCENE.yaml and SURVEY.yaml: read and validated against ``survey.schema.yaml``; the survey as frozen settings.

Both files are validated like the study config (:func:`waveforest.config.validate_document`:
defaults filled, the first violation reported as ``file: key/path: what was expected``);
relative file names inside them are resolved against the YAML file's folder. A scanner value
left null comes from the preset (:func:`als60`).
"""

from __future__ import annotations

import copy
import functools
from dataclasses import dataclass, fields
from pathlib import Path

import yaml

from waveforest.config import YamlLoader, validate_document
from waveforest.errors import WaveforestError
from waveforest.io.las.write import SPACING_TOL_PS, wkt_problem
from waveforest.model.forward import SensorSettings
from waveforest.sensor.reference import ReferenceSystem

SCHEMA_PATH = Path(__file__).parents[1] / "survey.schema.yaml"


AGC_LAW = (120.0, 0.0155)
"""The ``als60`` preset's AGC gain law ``gain = 1 + (AGC - a) b`` (docs/method.md Eq. 1): a of
the study's 2010 datasets and the median b of its nine."""

AGC_RANGE = (1, 255)
"""Recorded AGC values (8-bit ``user_data``; 0 reads as "no AGC")."""


class SurveyError(WaveforestError):
    """A scene, survey or survey input that cannot be used (one line: file, field, expected)."""


@functools.cache
def _schemas() -> dict:
    with open(SCHEMA_PATH) as fh:
        return yaml.load(fh, Loader=YamlLoader)


def schema(which: str) -> dict:
    """The closed JSON schema of ``"scene"`` or ``"survey"`` (a fresh copy)."""
    return copy.deepcopy(_schemas()[which])


SCENE_SCHEMA = "scene"
SURVEY_SCHEMA = "survey"


def read_document(path: str | Path, which: str) -> dict:
    """The validated, default-filled mapping of a SCENE.yaml (``which="scene"``) or SURVEY.yaml."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SurveyError(f"{path}: cannot read the {which} file ({getattr(exc, 'strerror', None) or exc})") from None
    try:
        doc = yaml.load(text, Loader=YamlLoader)
    except yaml.YAMLError as exc:
        raise SurveyError(f"{path}: not valid YAML ({' '.join(str(exc).split())})") from None
    doc = {} if doc is None else doc
    if not isinstance(doc, dict):
        raise SurveyError(f"{path}: expected a mapping of {which} keys at the top level")
    return validate_document(_schemas()[which], doc, str(path), SurveyError)


def resolve(base: Path, name) -> Path | None:
    """``name`` relative to ``base`` (absolute and ``~`` names as given); None stays None."""
    if name is None:
        return None
    p = Path(name).expanduser()
    return p if p.is_absolute() else base / p


@dataclass(frozen=True)
class Leg:
    """A straight leg at constant altitude (m, scene frame) and ground speed (m/s)."""

    start: tuple[float, float]
    end: tuple[float, float]
    altitude_m: float
    speed_m_s: float


@dataclass(frozen=True)
class Scanner:
    """Scanner and receiver of a survey (every value resolved against the preset).

    ``plane_hdrf`` and ``plane_dn`` scale the Gaussian S(t): a nadir Lambertian plane of HDRF
    ``plane_hdrf`` at 1200 m peaks at ``gain * plane_dn`` DN above the noise mean.
    """

    pulse_rate_hz: float
    pattern: str
    scan_angle_deg: float
    scan_frequency_hz: float
    divergence_mrad: float
    pulse_fwhm_ns: float
    system_waveform: Path | None
    sampling_ns: float
    bits: int
    gain: float
    noise_mean: float
    noise_sd: float
    record_ns: float
    cfd_fraction: float
    cfd_arming_sd: float
    plane_hdrf: float
    plane_dn: float
    agc_law_a: float
    agc_law_b: float

    @property
    def agc(self) -> int:
        """The AGC value recorded with every pulse: the integer nearest to the one whose gain
        under the AGC law (Eq. 1) is ``gain``, clipped to :data:`AGC_RANGE`."""
        v = round(self.agc_law_a + (self.gain - 1.0) / self.agc_law_b)
        return int(min(max(v, AGC_RANGE[0]), AGC_RANGE[1]))


@dataclass(frozen=True)
class Survey:
    """A validated SURVEY.yaml (docs/survey.md)."""

    source: Path
    seed: int
    legs: tuple[Leg, ...]
    trajectory: Path | None
    start_gps_time_s: float
    turn_s: float
    trajectory_hz: float
    scanner: Scanner
    tolerance: float | None
    rays_per_pulse: int | None
    max_order: int | None
    tile_m: float
    las_version: str
    waveforms: str
    laz: bool
    truth: bool
    crs_wkt: str | None
    chunk_pulses: int


def als60(sensor: SensorSettings, reference: ReferenceSystem) -> dict:
    """The ``als60`` preset: the study's ALS60 (docs/method.md §(a)) with the configured receiver.

    Scan zenith 15 deg, divergence 0.15 mrad, 1-ns sampling, 8 bits (``sensor.digitizer_max``),
    record length, CFD fraction and arming from the config's ``sensor`` section, the Gaussian
    S(t) and noise of ``sensitivity.reference_system``; 120 kHz pulses on an oscillating mirror
    at 40 Hz (an ALS60 setting for a ~1200 m flight).
    """
    return dict(pulse_rate_hz=120_000.0, pattern="oscillating", scan_angle_deg=15.0, scan_frequency_hz=40.0,
                divergence_mrad=0.15, pulse_fwhm_ns=reference.fwhm_ns, system_waveform=None, sampling_ns=1.0,
                bits=8 if sensor.digitizer_max <= 255 else 16, gain=1.0, noise_mean=reference.noise_mean,
                noise_sd=reference.noise_sd, record_ns=sensor.record_ns, cfd_fraction=sensor.cfd.fraction,
                cfd_arming_sd=sensor.cfd.arming_sd, plane_hdrf=reference.plane_hdrf, plane_dn=reference.plane_dn,
                agc_law_a=AGC_LAW[0], agc_law_b=AGC_LAW[1])


PRESETS = {"als60": als60}
"""Scanner presets: name -> function of the configured sensor and reference system."""


def load_survey(path: str | Path, sensor: SensorSettings, reference: ReferenceSystem) -> Survey:
    """Read and validate SURVEY.yaml (:class:`SurveyError`: file, key and what was expected)."""
    path = Path(path)
    doc = read_document(path, SURVEY_SCHEMA)
    base = path.parent
    p, s, q, o = doc["platform"], doc["scanner"], doc["quality"], doc["output"]
    legs = tuple(Leg((float(g["start"][0]), float(g["start"][1])), (float(g["end"][0]), float(g["end"][1])),
                     float(g["altitude_m"]), float(g["speed_m_s"])) for g in p["legs"])
    if bool(legs) == (p["trajectory"] is not None):
        raise SurveyError(f"{path}: platform: expected exactly one of legs and trajectory")
    for i, g in enumerate(legs):
        if g.start == g.end:
            raise SurveyError(f"{path}: platform/legs/{i}: expected start and end to differ")
    preset = PRESETS[s["preset"]](sensor, reference) if s["preset"] is not None else {}
    values = {}
    for f in fields(Scanner):
        v = s.get(f.name)
        if v is None:
            v = preset.get(f.name)
        if v is None and f.name not in ("system_waveform",):
            if f.name in ("plane_hdrf", "plane_dn"):
                v = getattr(reference, f.name)
            elif f.name == "gain":
                v = 1.0
            elif f.name in ("agc_law_a", "agc_law_b"):
                v = dict(zip(("agc_law_a", "agc_law_b"), AGC_LAW))[f.name]
            else:
                raise SurveyError(f"{path}: scanner/{f.name}: expected a value (scanner preset is null)")
        values[f.name] = v
    values["system_waveform"] = resolve(base, values["system_waveform"])
    if values["system_waveform"] is not None and not values["system_waveform"].exists():
        raise SurveyError(f"{path}: scanner/system_waveform: {values['system_waveform']}: no such file")
    values["bits"] = int(values["bits"])
    for k in ("pulse_rate_hz", "scan_angle_deg", "scan_frequency_hz", "divergence_mrad", "pulse_fwhm_ns",
              "sampling_ns", "gain", "noise_mean", "noise_sd", "record_ns", "cfd_fraction", "cfd_arming_sd",
              "plane_hdrf", "plane_dn", "agc_law_a", "agc_law_b"):
        values[k] = float(values[k])
    trajectory = resolve(base, p["trajectory"])
    if trajectory is not None and not trajectory.exists():
        raise SurveyError(f"{path}: platform/trajectory: {trajectory}: no such file")
    ps = values["sampling_ns"] * 1000.0
    if abs(ps - round(ps)) > SPACING_TOL_PS:
        raise SurveyError(f"{path}: scanner/sampling_ns: {values['sampling_ns']:g} ns is not a whole number of "
                          f"picoseconds (LAS stores the sampling interval in ps); expected e.g. {round(ps) / 1000:g}")
    if o["crs_wkt"] is not None and (problem := wkt_problem(o["crs_wkt"], metric=True)):
        raise SurveyError(f"{path}: output/crs_wkt: {problem}")
    if trajectory is not None and p["start_gps_time_s"] is not None:
        raise SurveyError(f"{path}: platform/start_gps_time_s: expected null with a trajectory (its gps_time "
                          "column times the flight)")
    if o["laz"] and o["waveforms"] == "internal":
        raise SurveyError(f"{path}: output/laz: expected waveforms external with LAZ points")
    if q["tolerance"] is not None and q["rays_per_pulse"] is not None:
        raise SurveyError(f"{path}: quality: expected tolerance (an adaptive budget) or rays_per_pulse "
                          "(a fixed one), not both")
    return Survey(
        source=path, seed=int(doc["seed"]), legs=legs, trajectory=trajectory,
        start_gps_time_s=float(p["start_gps_time_s"] or 0.0), turn_s=float(p["turn_s"]),
        trajectory_hz=float(p["trajectory_hz"]), scanner=Scanner(**values),
        tolerance=q["tolerance"], rays_per_pulse=q["rays_per_pulse"], max_order=q["max_order"], tile_m=float(q["tile_m"]),
        las_version=str(o["las_version"]), waveforms=str(o["waveforms"]), laz=bool(o["laz"]),
        truth=bool(o["truth"]), crs_wkt=o["crs_wkt"], chunk_pulses=int(o["chunk_pulses"]))
