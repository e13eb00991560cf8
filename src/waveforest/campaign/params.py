"""Parameter files of the virtual campaign (``resources/campaign/``), loaded and checked.

Every number of the virtual campaign lives in one of these files, not in code:

=====================  ====================================================================
file                   content
=====================  ====================================================================
datasets.csv           Table 2 of the paper (verbatim columns) plus the flight plan of each
                       dataset: year, divergence, maximum scan zenith, flight azimuths,
                       minimum number of strips, strip overlap, ground speed, GPS start time
sensor_truth.csv       the sensor as it really behaves, per dataset: system pulse shape and
                       scale, noise, AGC law and loop, the DR discriminator (CFD, range walk,
                       timing jitter), DR intensity noise, per-strip positioning errors
targets.csv            reference target sites: material, years, nadir HDRF (empty for
                       AGC-only targets), true reflectance, calibration/AGC flags, size
design_counts.csv      field-sample counts per species and design of Table 1 (P10, S10, S12):
                       which species were sampled in which year
coverage.csv           per dataset and species, the share of its field samples that a strip
                       whose swath holds them records (Table 3's counts; design counts only)
layout.yaml            study area, stands, terrain, sample rules, flight-path parameters
=====================  ====================================================================

The meaning of each column of ``sensor_truth.csv`` is in :data:`SENSOR_COLUMNS`.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pandas as pd
import yaml

from waveforest import RESOURCES
from waveforest.errors import WaveforestError

CAMPAIGN_RESOURCES = RESOURCES / "campaign"
"""Folder of the campaign's parameter files."""

DATASET_COLUMNS = {
    "dataset": "name, year_altitude(hm)_sampling(ns) (Table 2)",
    "year": "campaign year",
    "mean_range_m": "mean range, m (Table 2)",
    "sd_range_m": "SD of range, m (Table 2)",
    "cv_intensity_pct": "CV of intensity due to range, % (Table 2)",
    "prf_khz": "pulse repetition frequency, kHz (Table 2)",
    "peak_power_kw": "peak power, kW (Table 2)",
    "pulse_width_fwhm_ns": "FWHM of the system waveform, ns (Table 2)",
    "footprint_diameter_m": "1/e footprint diameter at the mean range, m (Table 2)",
    "sampling_ns": "waveform sampling interval, ns (Table 2)",
    "pulse_density_m2": "waveform pulse density, 1/m^2 (Table 2)",
    "divergence_mrad": "full-angle 1/e beam divergence, mrad (docs/method.md §(a): 0.15)",
    "max_scan_zenith_deg": "largest scan zenith angle, degrees (docs/method.md §(a): 15)",
    "flight_azimuths_deg": "azimuths of the strips, degrees, space-separated, alternating (160 340)",
    "min_strips": "fewest strips flown over the area",
    "strip_overlap": "side overlap of neighbouring strips, fraction of the swath",
    "speed_m_s": "aircraft ground speed, m/s",
    "start_gps_time_s": "GPS time (s of the GPS week) of the first strip",
    "campaign_date": "date of the flight (docs/method.md §(a))",
}
"""Columns of ``datasets.csv`` and their meaning."""

SENSOR_COLUMNS = {
    "ground_amplitude_dn": "peak amplitude of a nadir Lambertian rho=0.30 plane at the mean range "
                           "and unit gain, DN (sets the scale of S(t); 2012: similar levels, the paper's "
                           "constant ground irradiance)",
    "pulse_tail_ratio": "exponential tail of the system pulse: tau / sigma of its Gaussian rise",
    "afterpulse_rel": "relative amplitude of the weak after-pulse (ringing) of the system pulse",
    "afterpulse_delay_fwhm": "delay of the after-pulse after the main peak, in FWHMs",
    "noise_mean_dn": "mean of the additive waveform noise c, DN",
    "noise_sd_dn": "SD of the additive waveform noise c, DN",
    "agc_law_a": "reference AGC of the true gain law 1 + (AGC - a) b (Eq. 1)",
    "agc_law_b": "true relative gain change per AGC unit (Eq. 1)",
    "agc_bg_mean": "mean AGC that the terrain outside the simulated sites drives the loop to",
    "agc_bg_sd": "SD of that terrain-driven AGC level (Ornstein-Uhlenbeck process in time)",
    "agc_bg_tau_s": "correlation time of the terrain-driven AGC level, s",
    "agc_loop_tau_s": "relaxation time of the AGC loop towards the terrain level, s",
    "agc_loop_gain": "AGC units the loop moves per unit of ln(observed peak / set point)",
    "agc_setpoint_dn": "peak amplitude the AGC loop drives the signal towards, DN",
    "agc_jitter_sd": "SD of the pulse-to-pulse AGC fluctuation, AGC units",
    "cfd_fraction": "fraction f of the sensor's DR constant fraction discriminator",
    "cfd_delay_fwhm": "delay of the DR discriminator, in system-pulse FWHMs",
    "cfd_arm_dn": "arming threshold of the DR discriminator, DN above the baseline",
    "cfd_dead_time_fwhm": "dead time between DR echoes, in system-pulse FWHMs",
    "walk_coef_m": "range walk, m per unit ln(echo amplitude / walk_ref_dn) (negative: strong echoes early)",
    "walk_ref_dn": "echo amplitude with zero range walk, DN",
    "walk_max_m": "largest absolute range walk, m",
    "timing_jitter_ns": "SD of the DR timing jitter, ns of two-way time",
    "intensity_noise_dn": "SD of the DR intensity around the echo's peak amplitude, DN",
    "strip_xy_sd_m": "SD of the per-strip horizontal positioning error after strip matching, m",
    "strip_z_sd_m": "SD of the per-strip vertical positioning error after GNSS Z correction, m",
}
"""Columns of ``sensor_truth.csv`` (one row per dataset) and their meaning."""

TARGET_COLUMNS = {
    "site": "name of the physical target site",
    "material": "material (tarp, asphalt, sand, bitumen_roof, old_asphalt, fine_sand, grass)",
    "years": "campaign years in which the site was flown, space-separated",
    "hdrf": "published nadir HDRF at 1064 nm (docs/method.md §(e)); empty for AGC-only targets",
    "true_rho": "reflectance of the Lambertian plane in the truth (= hdrf where known)",
    "calibration": "1 = used to calibrate S(t) (Eq. 8)",
    "agc": "1 = homogeneous target for the AGC fit (Eq. 1)",
    "radius_m": "selection radius around the centre, m",
    "side_m": "side of the square target surface, m",
    "on_ground_rho": "reflectance of the ground around a small target (tarps); empty = none",
    "source": "where the numbers come from",
}
"""Columns of ``targets.csv`` (resource) and their meaning."""


class CampaignParamsError(WaveforestError):
    """A parameter file of the virtual campaign that cannot be used."""


def _read_csv(name: str, columns) -> pd.DataFrame:
    path = CAMPAIGN_RESOURCES / name
    if not path.exists():
        raise CampaignParamsError(f"{path}: no such parameter file")
    df = pd.read_csv(path, keep_default_na=True)
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise CampaignParamsError(f"{path}: missing column(s) {', '.join(missing)}")
    return df


@lru_cache(maxsize=1)
def _datasets_all() -> pd.DataFrame:
    ds = _read_csv("datasets.csv", DATASET_COLUMNS)
    sensor = _read_csv("sensor_truth.csv", ["dataset", *SENSOR_COLUMNS])
    missing = sorted(set(ds["dataset"]) - set(sensor["dataset"]))
    if missing:
        raise CampaignParamsError(
            f"{CAMPAIGN_RESOURCES / 'sensor_truth.csv'}: no row for dataset(s) {', '.join(missing)}")
    df = ds.merge(sensor, on="dataset", how="left", validate="one_to_one")
    df["dataset"] = df["dataset"].astype(str)
    df["year"] = df["year"].astype(int)
    num = [c for c in df.columns if c not in ("dataset", "flight_azimuths_deg", "campaign_date")]
    bad = [c for c in num if not np.all(np.isfinite(df[c].to_numpy(dtype=float)))]
    if bad:
        raise CampaignParamsError(f"{CAMPAIGN_RESOURCES}: non-numeric or empty values in {', '.join(bad)}")
    if np.any(df["max_scan_zenith_deg"] <= 0) or np.any(df["max_scan_zenith_deg"] >= 45):
        raise CampaignParamsError("datasets.csv: max_scan_zenith_deg must be in (0, 45)")
    return df


def load_datasets(names: list[str] | tuple[str, ...] | None = None) -> pd.DataFrame:
    """Flight plan and true sensor parameters of the datasets, one row each, in ``names`` order.

    Parameters
    ----------
    names
        Dataset names (e.g. ``"2010_12_1"``); None = all nine.

    Raises
    ------
    CampaignParamsError
        A name that the campaign does not know (the message lists the known ones).
    """
    df = _datasets_all()
    if names is None:
        return df.copy()
    known = list(df["dataset"])
    unknown = [n for n in names if n not in known]
    if unknown:
        raise CampaignParamsError(
            f"datasets: {', '.join(map(repr, unknown))} not in the virtual campaign; "
            f"known: {', '.join(known)}")
    if len(set(names)) != len(names):
        raise CampaignParamsError("datasets: a dataset is listed twice")
    return df.set_index("dataset").loc[list(names)].reset_index()


def load_targets() -> pd.DataFrame:
    """The reference target sites (``targets.csv`` resource)."""
    df = _read_csv("targets.csv", TARGET_COLUMNS)
    if np.any(df["true_rho"] <= 0) or np.any(df["true_rho"] > 1):
        raise CampaignParamsError("targets.csv: true_rho must be in (0, 1]")
    if np.any(df["radius_m"] > df["side_m"] / 2):
        raise CampaignParamsError("targets.csv: the disc of radius_m must lie inside the target square (side_m)")
    df["years"] = df["years"].astype(str)
    return df


COVERAGE_COLUMNS = {
    "dataset": "dataset name (datasets.csv)",
    "species": "species slug (design_counts.csv), or * for every species of the dataset not listed",
    "coverage": "probability that a strip whose swath holds a field sample records its pulses, in [0, 1]",
}
"""Columns of ``coverage.csv`` and their meaning (absent rows: 1)."""


@lru_cache(maxsize=1)
def _coverage() -> pd.DataFrame:
    path = CAMPAIGN_RESOURCES / "coverage.csv"
    df = _read_csv("coverage.csv", COVERAGE_COLUMNS)[list(COVERAGE_COLUMNS)]
    df["dataset"], df["species"] = df["dataset"].astype(str), df["species"].astype(str)
    c = pd.to_numeric(df["coverage"], errors="coerce").to_numpy(float)
    if not np.all((c >= 0) & (c <= 1)):
        raise CampaignParamsError(f"{path}: column coverage: expected numbers in [0, 1]")
    unknown = sorted(set(df["dataset"]) - set(_datasets_all()["dataset"]))
    if unknown:
        raise CampaignParamsError(f"{path}: column dataset: unknown dataset(s) {', '.join(unknown)}")
    slugs = set(load_design_counts()["slug"]) | {"*"}
    unknown = sorted(set(df["species"]) - slugs)
    if unknown:
        raise CampaignParamsError(f"{path}: column species: unknown slug(s) {', '.join(unknown)} (or *)")
    if df.duplicated(["dataset", "species"]).any():
        raise CampaignParamsError(f"{path}: a (dataset, species) pair is listed twice")
    df["coverage"] = c
    return df


def coverage(dataset: str, species) -> np.ndarray:
    """Coverage (``coverage.csv``) of field samples of ``species`` (array of slugs) in ``dataset``:
    the species' own row, else the dataset's ``*`` row, else 1. Shape of ``species``."""
    df = _coverage()
    rows = df[df["dataset"] == dataset]
    table = dict(zip(rows["species"], rows["coverage"]))
    default = table.pop("*", 1.0)
    sp = pd.Series(np.asarray(species, dtype=object))
    return sp.map(table).fillna(default).to_numpy(float)


def load_design_counts() -> pd.DataFrame:
    """Field-sample counts per species slug and design (Table 1: P10, S10, S12)."""
    return _read_csv("design_counts.csv", ["slug", "name", "P10", "S10", "S12"])


@lru_cache(maxsize=1)
def _layout() -> dict:
    path = CAMPAIGN_RESOURCES / "layout.yaml"
    if not path.exists():
        raise CampaignParamsError(f"{path}: no such parameter file")
    with open(path) as fh:
        data = yaml.safe_load(fh)
    for section in ("area", "stands", "targets", "terrain", "samples", "flight"):
        if section not in data:
            raise CampaignParamsError(f"{path}: section {section!r} missing")
    return data


def load_layout() -> dict:
    """The study-area, stand, terrain, sample and flight parameters (``layout.yaml``)."""
    return yaml.safe_load(yaml.safe_dump(_layout()))  # a deep copy


def azimuths(row: pd.Series) -> list[float]:
    """Strip azimuths of a dataset row, degrees (alternating in flight order)."""
    return [float(v) for v in str(row["flight_azimuths_deg"]).split()]
