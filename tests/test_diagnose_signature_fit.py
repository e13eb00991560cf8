"""The fit along a signature (waveforest.diagnose.signature_fit) and the search's step 5."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from fixtures.study import SyntheticStudy

from waveforest.diagnose.power import PowerSettings, detection_limits
from waveforest.diagnose.search import SearchSettings, search
from waveforest.diagnose.signature_fit import zero_crossings

U = np.array([0.0, 0.25, 0.5, 0.75, 1.0])


def test_zero_crossings_known_answers():
    line = 2.0 * (0.6 - U)
    assert zero_crossings(U, line[None], 0.0)[0] == pytest.approx(0.6)
    # a square law is read linearly between the neighbouring grid values
    square = 0.09 - U**2
    assert zero_crossings(U, square[None], 0.0)[0] == pytest.approx(0.25 + 0.25 * 0.0275 / 0.1875)
    # off inside the range: the crossing nearest it, on either side
    v = np.linspace(-1.0, 1.0, 9)
    two = (v - 0.4) * (v + 0.8)
    assert zero_crossings(v, two[None], 0.0)[0] == pytest.approx(0.4, abs=0.02)
    assert zero_crossings(v, two[None], -0.9)[0] == pytest.approx(-0.8, abs=0.02)
    # no crossing; rows are independent curves
    out = zero_crossings(U, np.stack([U + 1.0, line]), 0.0)
    assert np.isnan(out[0]) and out[1] == pytest.approx(0.6)


STUDY = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
# the gap cannot name: no candidate removes fifty times the excess gap
BLIND_GAP = SearchSettings(n_boot=100, rounds=1, min_relative_reduction=50.0)


@pytest.fixture(scope="module")
def signature_test():
    cal = {}
    detection_limits(STUDY.keys, STUDY.simulate, BLIND_GAP, PowerSettings(replicates=8, values=1), 3,
                     calibration=cal)
    return cal["signature"]


def test_an_effect_the_gap_does_not_name_is_named_along_its_signature(signature_test):
    real = STUDY.real({"hotspot": 1.3})
    alone = search(STUDY.keys, real, STUDY.simulate, BLIND_GAP, seed=3, significant=True)
    assert alone.verdict == "unexplained" and not alone.named
    res = search(STUDY.keys, real, STUDY.simulate, BLIND_GAP, seed=3, significant=True, signature=signature_test)
    assert res.verdict == "named" and [e.name for e in res.named] == ["hotspot"]
    e = res.named[0]
    assert e.ci_low <= 1.3 <= e.ci_high and e.ci_low > 1.0, (e.value, e.ci_low, e.ci_high)
    assert e.along_signature.startswith("along its signature") and "on the model before it" in e.along_signature
    again = search(STUDY.keys, real, STUDY.simulate, BLIND_GAP, seed=3, significant=True, signature=signature_test)
    assert (again.named[0].value, again.named[0].ci_low) == (e.value, e.ci_low)


def test_no_effect_and_an_unproducible_disagreement_are_not_named_along_a_signature(signature_test):
    none = search(STUDY.keys, STUDY.real({}), STUDY.simulate, replace(BLIND_GAP, rounds=2), seed=3,
                  significant=True, signature=signature_test)
    assert none.named == [], [(e.name, e.value) for e in none.named]
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1, perturb={"FWHM": 1.0, "H": -1.0})
    res = search(study.keys, study.real({}), study.simulate, BLIND_GAP, seed=3, significant=True,
                 signature=signature_test)
    assert res.verdict == "unexplained" and res.named == [], [(e.name, e.value, e.along_signature) for e in res.named]
    assert "along the signatures" in res.reason
