"""The raw simulator's phase contrast is the one single-distance phase retrieval inverts: Paganin's filter
applied to its noiseless intensity gives back the exact projection of the liquid and its bubbles (the wave
sampled finely enough), and a wave sampled as coarsely as the detector's half-pixel does not (its aliased phase
at the bubbles' edges loses the phase contrast, so the retrieval blurs)."""

import numpy as np
import pytest

import bubsub.core.foam.raw as raw
from bubsub.core import MeshProjector
from bubsub.core.prep.phase import paganin_filter
from bubsub.core.projection.geometry import ScanGeometry


def _retrieved_and_exact(**kw):
    """Paganin-retrieved line integrals of the simulator's noiseless intensity (4 views, 12 um pixels, 16 keV,
    300 mm) and the exact projection of the same liquid cylinder and bubbles (the projector, no wave)."""
    s = raw.raw_settings(n_angles=4, rows=1, cols=160, pixel_size=0.012, axis_offset=3.3, distance=300.0,
                         container_radius=0.85, wall=0.0, supersample=2, **kw)
    phantom = raw.disc_foam(0, 0.85, n_bubbles=24, radius_range=(0.07, 0.13))
    seen = {}
    detector = raw._detector

    def keep(intensity, theta, settings, rng):
        seen["intensity"] = intensity
        return detector(intensity, theta, settings, rng)

    try:
        raw._detector = keep
        raw.simulate_raw(phantom, s)
    finally:
        raw._detector = detector
    retrieved = -np.log(paganin_filter(seen["intensity"][:, None, :], pixel_size=s.pixel_size, energy=s.energy,
                                       distance=s.distance, delta_beta=s.delta_beta)[:, 0])
    g = ScanGeometry.parallel(np.radians(np.linspace(0, 180, s.n_angles, endpoint=False)),
                              pixel_size=s.pixel_size, cols=s.cols)
    vec = np.array(g.vectors)
    vec[:, 2:4] += (s.cols / 2 - 0.5 - s.axis_column) * vec[:, 4:6]  # the axis at axis_column
    g = ScanGeometry.from_astra("parallel_vec", vec, det_count=s.cols)
    u = (np.arange(s.cols) - s.axis_column) * s.pixel_size
    liquid = s.liquid_mu * 2 * np.sqrt(np.maximum(s.container_radius ** 2 - u ** 2, 0))
    exact = liquid[None] + MeshProjector(g, supersampling=4).forward(list(phantom.bubbles))
    inner = np.abs(u) < 0.8  # away from the cylinder's own edge
    return retrieved[:, inner], exact[:, inner]


def _amplitude(a, b, band):
    """The least-squares gain of ``a`` on ``b`` in a band of spatial frequencies (cycles per pixel)."""
    f = np.fft.rfftfreq(a.shape[1])
    keep = (f >= band[0]) & (f < band[1])
    fa, fb = np.fft.rfft(a, axis=1)[:, keep], np.fft.rfft(b, axis=1)[:, keep]
    return float(np.real(np.sum(fa * fb.conj())) / np.sum(np.abs(fb) ** 2))


def test_the_simulated_phase_contrast_is_what_paganins_retrieval_inverts():
    retrieved, exact = _retrieved_and_exact()
    assert raw.wave_supersampling(raw.raw_settings(pixel_size=0.012, supersample=2)) == 8  # 1.5 um
    assert np.abs(retrieved - exact).mean() < 0.003  # 0.0040 with the wave at 6 um; bubbles 0.01-0.03 deep
    assert _amplitude(retrieved, exact, (0.04, 0.12)) == pytest.approx(1.0, abs=0.08)


def test_a_wave_sampled_at_half_the_pixel_aliases_and_the_retrieval_blurs():
    retrieved, exact = _retrieved_and_exact(wave_pixel=0.006)
    assert _amplitude(retrieved, exact, (0.04, 0.12)) < 0.8  # 0.96 at 1.5 um
    with pytest.raises(ValueError, match="wave_pixel must be positive"):
        raw.raw_settings(wave_pixel=0.0)
