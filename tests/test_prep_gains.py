"""Pixel gains that the flats do not show (core/prep/gains.py, ``bubsub prepare --double-flat``): recovered from a
mean log transmission against the gains put in, their checks, the option's checks, and a raw scan of a foam wider
than the detector reconstructed better with them divided out before phase retrieval than without."""

import numpy as np
import pytest

from bubsub.core.prep import prepare_options
from bubsub.core.prep.gains import GAIN_MEDIAN_COLUMNS, stripe_gains


def test_the_gains_are_the_fine_part_of_the_mean_log_transmission():
    # a liquid cylinder's smooth mean projection, a gentle flat-field drift, and a few pixels off by 1-5 %
    cols = 300
    u = np.linspace(-1.0, 1.0, cols)
    smooth = -0.1 * 2 * np.sqrt(1.6 ** 2 - u ** 2) + 0.02 * np.sin(3 * u)
    rng = np.random.default_rng(0)
    log_gain = np.zeros((2, cols))
    where = rng.choice(cols, 12, replace=False)
    log_gain[np.arange(12) % 2, where] = rng.choice([-1, 1], 12) * rng.uniform(0.01, 0.05, 12)
    gains = stripe_gains(np.stack([smooth, smooth]) + log_gain)
    assert gains.shape == (2, cols) and gains.dtype == np.float32
    error = np.abs(np.log(gains.astype(np.float64)) - log_gain)
    # a gain in a pixel's window moves its running median by one rank: at most the mean's change over a column
    assert error.max() < 2e-3 and np.median(error) < 1e-5  # 0.0014 beside a gain near the side; 0 elsewhere


def test_a_feature_wider_than_the_median_is_the_samples_not_a_gain():
    m = np.zeros((1, 100))
    m[0, 40:40 + 2 * GAIN_MEDIAN_COLUMNS] = -0.2  # a bubble's step in the mean projection
    assert np.abs(np.log(stripe_gains(m))).max() < 1e-6


@pytest.mark.parametrize("mean_log, width, message", [
    (np.zeros(10), 9, "rows, cols"), (np.zeros((2, 10)), 4, "odd"), (np.zeros((2, 10)), 1, "odd"),
    (np.zeros((2, 10)), 9.0, "odd")])
def test_bad_gain_inputs_are_named(mean_log, width, message):
    with pytest.raises(ValueError, match=message):
        stripe_gains(mean_log, width)


def test_the_option_is_checked():
    assert prepare_options().double_flat == "auto"
    assert prepare_options(double_flat="off").double_flat == "off"
    with pytest.raises(ValueError, match="double_flat must be one of"):
        prepare_options(double_flat="yes")


def test_a_local_scans_stripes_divided_out_before_phase_retrieval_leave_no_spikes(tmp_path):
    # seed 31 of `python -m bubsub.bench fov --local`: without the gains divided out, the stripes that phase
    # retrieval spreads differently in each view draw three interior bubbles into spikes along their ring
    from bubsub.bench.fov_local import local_case

    with_gains = local_case(tmp_path / "on", 31)
    without = local_case(tmp_path / "off", 31, double_flat="off")
    assert with_gains["found"] == with_gains["truth"] and with_gains["spurious"] == 0
    assert with_gains["ddi"] < 0.05  # 0.040
    # without: 0.061 alone, 0.048 after the rest of the suite (the fit's path follows float-level differences)
    assert without["ddi"] > with_gains["ddi"]
