"""The system waveform S(t): analytic Gaussian, width changes at constant energy, persistence."""

import math

import numpy as np
import pytest

from waveforest.errors import WaveforestError
from waveforest.sensor import CFDParams, SystemWaveform, gaussian_system_waveform, load_system_waveform

FWHM_PER_SD = 2.0 * math.sqrt(2.0 * math.log(2.0))
CFD_ZERO_TOL_NS = 0.005


def skewed_pulse(fwhm_rise=4.0, tail_ns=3.0, peak=2.0e9):
    """A non-Gaussian pulse: Gaussian rise, exponential tail (like the campaign's true pulse)."""
    t = 0.05 * np.arange(-600, 1200)
    s = np.where(t < 0, np.exp(-0.5 * (t / (fwhm_rise / FWHM_PER_SD)) ** 2), np.exp(-t / tail_ns))
    return SystemWaveform(t, peak * s)


@pytest.mark.parametrize("fwhm", [1.4, 4.0, 7.2, 10.1, 14.0])
def test_gaussian_fwhm_energy_and_cfd_origin(fwhm):
    peak = 1.5e9
    sw = gaussian_system_waveform(fwhm, peak)
    assert sw.fwhm_ns == pytest.approx(fwhm, rel=1e-3)
    assert sw.energy == pytest.approx(peak * fwhm / FWHM_PER_SD * math.sqrt(2 * math.pi), rel=1e-6)
    assert sw.peak == pytest.approx(peak, rel=1e-3)
    assert abs(sw.cfd_time_ns()) < CFD_ZERO_TOL_NS  # t = 0 is the CFD time of a spike
    assert np.allclose(np.diff(sw.t_ns), 0.05)


def test_gaussian_placed_for_a_non_default_cfd():
    cfd = CFDParams(fraction=0.3, delay_ns=2.0)
    sw = gaussian_system_waveform(7.2, 1.0, cfd=cfd)
    assert abs(sw.cfd_time_ns(cfd)) < CFD_ZERO_TOL_NS
    assert sw.t_peak_ns > 0.5  # f = 0.3, d = 2 ns: the crossing lies well before the peak


@pytest.mark.parametrize("new_fwhm", [1.4, 3.5, 10.5, 14.0])
def test_stretched_keeps_energy_and_shape(new_fwhm):
    sw = skewed_pulse()
    st = sw.stretched(new_fwhm)
    assert st.fwhm_ns == pytest.approx(new_fwhm, rel=5e-3)
    assert st.energy == pytest.approx(sw.energy, rel=2e-3)
    k = new_fwhm / sw.fwhm_ns
    assert st.peak == pytest.approx(sw.peak / k, rel=2e-2)
    back = st.stretched(sw.fwhm_ns)
    assert back.energy == pytest.approx(sw.energy, rel=3e-3)
    g = gaussian_system_waveform(7.2, 1.0).stretched(new_fwhm)  # CFD delay follows the width: t = 0 stays
    assert abs(g.cfd_time_ns()) < CFD_ZERO_TOL_NS
    same = sw.stretched(sw.fwhm_ns)
    assert np.allclose(same.s, sw.s) and np.allclose(same.t_ns, sw.t_ns)


def test_aligned_to_cfd_and_shift():
    sw = skewed_pulse()
    al = sw.aligned_to_cfd()
    assert abs(al.cfd_time_ns()) < CFD_ZERO_TOL_NS
    assert al.energy == pytest.approx(sw.energy)
    assert sw.shifted(2.5).t_peak_ns == pytest.approx(sw.t_peak_ns + 2.5)


def test_save_load_round_trip(tmp_path):
    sw = skewed_pulse()
    sw.s_sd = 0.01 * sw.s
    sw.meta = {"dataset": "2010_12_1", "n_pulses": 12}
    p = sw.save(tmp_path / "s.parquet")
    back = load_system_waveform(p)
    assert np.array_equal(back.t_ns, sw.t_ns) and np.array_equal(back.s, sw.s) and np.array_equal(back.s_sd, sw.s_sd)
    assert back.meta == sw.meta
    g = gaussian_system_waveform(7.2, 3.0)
    back = load_system_waveform(g.save(tmp_path / "g.parquet"))
    assert back.s_sd is None and back.fwhm_ns == pytest.approx(7.2, rel=1e-3)


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="spaced"):
        SystemWaveform(np.arange(10) * 0.1, np.ones(10))
    with pytest.raises(ValueError, match="equal length"):
        SystemWaveform(np.arange(10) * 0.05, np.ones(9))
    with pytest.raises(ValueError, match="fwhm_ns"):
        gaussian_system_waveform(-1.0, 1.0)
    with pytest.raises(WaveforestError, match="no such"):
        load_system_waveform(tmp_path / "missing.parquet")
    (tmp_path / "bad.parquet").write_text("not parquet")
    with pytest.raises(WaveforestError, match="Parquet"):
        load_system_waveform(tmp_path / "bad.parquet")
