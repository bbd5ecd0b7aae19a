"""ReconstructionSettings: immutable, refused when made with a value no scan accepts."""

import dataclasses

import pytest

from bubsub.clients.pipeline.inputs.checks import check_settings
from bubsub.clients.pipeline.dynamic4d.chain import DynamicSettings
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings


def test_settings_cannot_change_after_they_are_made():
    s = ReconstructionSettings(iterations=12)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.iterations = -1
    assert s.iterations == 12
    assert dataclasses.replace(s, levels=3).levels == 3 and s.levels == 2


@pytest.mark.parametrize("field, value, words", [
    ("iterations", -1, "--iterations"),
    ("levels", 5, "--levels must be at most 4"),
    ("facet_pixels", float("nan"), "--facet-pixels"),
    ("supersampling", 0, "--supersampling"),
    ("control_points", 2, "--control-points"),
    ("detector", "blob", "--detector must be 'auto', 'log' or 'dt'"),
    ("holdout", "third", "--holdout must be 'odd' or 'even'"),
    ("fit_rtol", 1.5, "--fit-rtol"),
    ("radius", -0.1, "radius must be a positive number of mm"),
])
def test_a_value_no_scan_accepts_is_refused_when_made_and_when_replaced(field, value, words):
    with pytest.raises(ValueError, match=words):
        ReconstructionSettings(**{field: value})
    with pytest.raises(ValueError, match=words):  # dataclasses.replace makes new settings: checked again
        dataclasses.replace(ReconstructionSettings(), **{field: value})
    with pytest.raises(ValueError, match=words):  # the 4D settings hold static settings of the same kind
        DynamicSettings(**{field: value})


def test_what_needs_the_scans_dimension_is_checked_with_it():
    s = ReconstructionSettings(control_points=9)  # a 2D curve's; no 3D icosphere has 9 vertices
    check_settings(s, 2)
    with pytest.raises(ValueError, match=r"one of \[12, 42, 162\]"):
        check_settings(s, 3)
