"""The one contrast-sign check (core/contrast.py) that prepare and reconstruct share."""

import numpy as np
import pytest

from bubsub.core import MeshProjector, ScanGeometry, sphere_surface
from bubsub.core.contrast import contrast_sign_error, signal_masses


@pytest.fixture(scope="module")
def bubble_data():
    g = ScanGeometry.parallel(np.linspace(0, np.pi, 6, endpoint=False), pixel_size=0.1, cols=32, rows=16)
    clean = MeshProjector(g).forward([sphere_surface((0.2, 0, 0), 0.6, -0.1)])  # gas: negative line integrals
    noise = np.random.default_rng(0).normal(0, 0.002, clean.shape).astype(np.float32)
    return clean, noise


def test_masses_are_the_sums_beyond_the_noise():
    x = np.array([0.5, -0.2, 0.05, -0.01, 0.0])
    assert signal_masses(x) == pytest.approx((0.55, 0.21))
    # beyond +-0.1 only: 0.5 - 0.1 and 0.2 - 0.1
    assert signal_masses(x, 0.1) == pytest.approx((0.4, 0.1))


def test_a_negative_contrast_agrees_with_gas_bubbles_and_a_positive_one_does_not(bubble_data):
    clean, noise = bubble_data
    data = clean + noise
    assert contrast_sign_error(-0.1, data) is None
    message = contrast_sign_error(0.1, data)
    assert "+0.1 1/mm disagrees with the data (wrong sign)" in message and "mostly negative" in message
    # the liquid's projection left in (positive everywhere): a negative contrast is refused
    assert "mostly positive" in contrast_sign_error(-0.1, -data + 1.0)


def test_noise_alone_is_no_signal(bubble_data):
    _, noise = bubble_data
    assert "no bubble signal" in contrast_sign_error(-0.1, noise, noise=10 * float(noise.std()))
    assert "no bubble signal" in contrast_sign_error(-0.1, np.zeros(8))
