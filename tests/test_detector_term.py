"""The detector's view-constant term of a local-tomography scan (clients/pipeline/static/detector_term.py):
recovered from the data less the true bubbles' projection where the foam is wider than the detector, and
nothing done (data, report) on a scan whose foam fits the detector."""

from types import SimpleNamespace

import numpy as np
import pytest

from bubsub.clients.pipeline.inputs.fov import local_tomography
from bubsub.clients.pipeline.static.detector_term import detector_term_phase, view_constant_residual
from bubsub.core import MeshProjector
from bubsub.core.foam.raw import disc_foam
from bubsub.core.projection.geometry import ScanGeometry

C = -0.1


def _scan(scale, *, seed=3, cols=96, pixel=0.02, angles=90, noise=0.003):
    """Exact projections (4 rays per pixel) of a 2D foam filling a disc of ``scale`` times the field of view's
    radius, its liquid taken out: ``(geometry, bubble data, bubbles)``."""
    g = ScanGeometry.parallel(np.linspace(0, np.pi, angles, endpoint=False), pixel_size=pixel, cols=cols)
    r_fov = 0.5 * cols * pixel
    phantom = disc_foam(seed, scale * r_fov, n_bubbles=60 if scale > 1 else 20,
                        radius_range=(0.08 * r_fov, 0.15 * r_fov), liquid_attenuation=-C)
    bubbles = list(phantom.bubbles)
    data = np.asarray(MeshProjector(g, supersampling=4).forward(bubbles), dtype=np.float64)
    data += np.random.default_rng(seed).normal(0.0, noise, data.shape)
    return g, data, bubbles


def _column_error(cols, seed=1):
    """A detector error the same in every projection: stripes (single columns off by 0.01-0.03) on a smooth
    curvature (a background 0.01 too flat at the sides)."""
    rng = np.random.default_rng(seed)
    s = np.linspace(-1, 1, cols)
    error = -0.01 * s ** 2
    error[rng.choice(cols, 6, replace=False)] += rng.choice([-1, 1], 6) * rng.uniform(0.01, 0.03, 6)
    return error


def test_a_foam_wider_than_the_detector_is_local_tomography_and_one_inside_is_not():
    _, wide, _ = _scan(1.5)
    _, inside, _ = _scan(0.8)
    assert local_tomography(wide, C)
    assert not local_tomography(inside, C)


def test_the_term_is_the_detector_error_when_the_bubbles_are_right():
    g, data, bubbles = _scan(1.5)
    error = _column_error(g.det_cols)
    projector = MeshProjector(g, supersampling=2)
    run = SimpleNamespace(projector=projector, data=(data + error[None]).astype(np.float32), report={})
    fit = SimpleNamespace(surfaces=bubbles, interrupted=False)
    refits = []

    def refit(r, surfaces):  # the true bubbles stay where they are
        refits.append(r.data.copy())
        return SimpleNamespace(surfaces=surfaces, interrupted=False)

    out, term = detector_term_phase(run, fit, refit, C, passes=2)
    assert out.surfaces is bubbles and len(refits) == 2
    # against the injected error: within the noise's mean over 90 views and the projectors' ray sampling
    assert np.sqrt(np.mean((term - error) ** 2)) < 0.1 * np.sqrt(np.mean(error ** 2))
    assert np.abs(term - error).max() < 0.004
    assert run.report["detector_term"]["passes"] == 2
    assert run.report["detector_term"]["rms"] == pytest.approx(np.sqrt(np.mean(error ** 2)), rel=0.1)
    # what the refit saw: the data less the term, the exact bubbles' projection plus noise
    assert np.abs(refits[-1] - data).mean(axis=0).max() < 0.004
    assert np.abs(view_constant_residual(projector, bubbles, run.data)).max() < 0.002


def test_a_scan_that_fits_the_detector_is_left_as_it_is():
    g, data, bubbles = _scan(0.8)
    data32 = (data + _column_error(g.det_cols)[None]).astype(np.float32)
    run = SimpleNamespace(projector=MeshProjector(g), data=data32, report={})
    fit = SimpleNamespace(surfaces=bubbles, interrupted=False)

    def refit(r, surfaces):
        raise AssertionError("no refit on a scan that fits the detector")

    out, term = detector_term_phase(run, fit, refit, C)
    assert out is fit and term == 0.0 and run.data is data32 and run.report == {}
    _, wide, _ = _scan(1.5)
    run = SimpleNamespace(projector=MeshProjector(g), data=wide.astype(np.float32), report={})
    out, term = detector_term_phase(run, fit, refit, C, enabled=False)  # the field-of-view model off
    assert out is fit and term == 0.0 and run.report == {}
