"""The README.md written into a campaign folder: the schema a user fills in for real data."""

from __future__ import annotations

README = """\
# Campaign folder

This folder holds one waveform-LiDAR campaign in the layout that every waveforest stage
reads. The virtual ALS60 campaign (`waveforest synthesize`) writes it; for real data, put
your own files in the same layout and set `data: <this folder>` in the study config.

| file | content |
|---|---|
| `datasets.csv` | one row per dataset (flight / sensor setting) |
| `fields.csv` | one row per field sample |
| `targets.csv` | one row per reference target (calibration and AGC targets) |
| `<dataset>.las` | LAS 1.3/1.4 with waveform packets (point format 4, 5, 9 or 10) |
| `<dataset>_trajectory.csv` | sensor trajectory of the dataset |
| `truth.json`, `truth_pulses.parquet` | virtual campaign only: what was really simulated (no analysis step reads them) |

Coordinates are projected metres (x east, y north, z up, elevations a.s.l.) in one system
for all files (the virtual campaign: ETRS-TM35FIN-like, EPSG:3067). Empty cells mean
"unknown".

## datasets.csv

| column | type | meaning |
|---|---|---|
| dataset | text | dataset name, e.g. `2010_12_1` (quote it in YAML configs) |
| year | integer | campaign year; field samples and targets of the same year belong to it |
| las_file | text | LAS waveform file, relative to this folder |
| trajectory_file | text | trajectory CSV, relative to this folder |
| mean_range_m | number | mean sensor-target range, m |
| pulse_width_fwhm_ns | number | FWHM of the emitted pulse (system waveform), ns |
| footprint_diameter_m | number | 1/e footprint diameter at the mean range, m |
| divergence_mrad | number | full-angle 1/e beam divergence, mrad (optional; default footprint / range) |
| sampling_ns | number | waveform sampling interval, ns |
| pulse_density_m2 | number | waveform pulse density, 1/m^2 (optional) |
| max_scan_zenith_deg | number | largest scan zenith angle, degrees (optional) |

## fields.csv

| column | type | meaning |
|---|---|---|
| sample_id | text | unique sample name |
| year | integer | year of the field visit (the datasets of that year see it) |
| stand_id | text | stand the sample lies in (optional) |
| design | text | P10 (2010 plots), S10 / S12 (isolated samples of 2010 / 2012) (optional) |
| species | text | species slug (e.g. `birch`, `raspberry`, `fireweed`, `scots_pine`, `sand_road`) |
| functional_group | text | conifer, broadleaf, low_green or low_barren_abiotic |
| x, y | number | GNSS position: tree base, or centre of a low-vegetation / ground sample, m |
| ground_z | number | GNSS ground elevation at the sample, m |
| height_m | number | maximum field height of the sample, m (0 for bare surfaces) |
| radius_m | number | sample radius, m (0.5 for S10, 1.0 for S12) |
| is_tree | 0/1 | 1 for single trees (echoes within 0.5 m of the base, above 1 m, are used) |
| canopy_cover_pct | number | visual canopy cover estimate, % (optional, may be empty) |

## targets.csv

| column | type | meaning |
|---|---|---|
| target_id | text | unique target name |
| year | integer | year in which the target was flown |
| material | text | tarp, asphalt, sand, bitumen_roof, old_asphalt, fine_sand, grass, ... |
| hdrf | number | nadir HDRF at 1064 nm (relative to Spectralon); empty for AGC-only targets |
| calibration | 0/1 | 1 = used to calibrate the system waveform S(t) (Eq. 8; needs hdrf) |
| agc | 0/1 | 1 = homogeneous target used to fit the AGC normalisation (Eq. 1) |
| x, y, z | number | target centre, m |
| radius_m | number | pulses whose first echo lies within this distance of (x, y) belong to the target, m |

## Trajectory CSV

Columns `gps_time, x, y, z`: the sensor position (m) at GPS time (s, the time of the LAS
points), in time order, dense enough for linear interpolation (the virtual campaign: 50 Hz).
Every pulse of the LAS file must lie within the time span of its trajectory.

## LAS waveform files

One point per discrete-return (DR) echo; the points of a pulse share its GPS time and its
waveform packet. The AGC value of a pulse is in the point attribute `user_data` (or an
extra-bytes dimension named in the config `agc.attribute`); intensity is the 8-bit DR
intensity. The virtual campaign writes LAS 1.4, point format 9, 8-bit samples, 256 ns
records (256 samples at 1 ns, 128 at 2 ns), waveform packets stored inside the file
(EVLR 65535), return point location and x(t), y(t), z(t) as the LAS specification defines
(anchor = point + location x (x(t), y(t), z(t)) is the first sample's position).

## truth.json (virtual campaign only)

seed; all ten hidden effects with their values (`effects`; `active_effects` lists those that
differ from off); per dataset: the true AGC law (`agc.law_a`, `agc.law_b`), the dataset mean
AGC `a` and the `b` that describes the same law with that reference (what `waveforest agc`
should recover), the noise mean and SD, the true system waveform S(t) (`system_waveform.t_ns`,
`.s` at unit gain and `.s_at_a_mean`, what `waveforest calibrate` should recover; t = 0 at
the sensor's DR time of a spike target, so a calibration aligned on DR times recovers it up
to the range walk at the targets' amplitude), the pulse FWHM, the DR discriminator, range
walk and timing jitter, the strips with their positioning offsets; the targets' true
reflectance; the true canopy cover of the samples. `truth_pulses.parquet` holds the true
geometry, AGC, gain and xy_error offset of every generated pulse.
"""


def readme_text() -> str:
    """The campaign folder's README.md."""
    return README
