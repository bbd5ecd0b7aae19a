"""The lateral-truncation rule judges the bubbles' signal at the detector's sides, not the liquid: scans whose
liquid (or its phase-retrieval blur) reaches the sides pass and reconstruct; a foam wider than the detector is
named local tomography; bubbles at a side in a few projections give one warning line and the reconstruction goes
on."""

import logging

import numpy as np
import pytest

from bubsub.core import MeshProjector
from bubsub.core.foam.containers import liquid_box, sphere_mesh
from bubsub.core.foam.raw import disc_foam, raw_settings, write_raw_simulation
from bubsub.core.io.scanfile import Scan, read_scan
from bubsub.core.projection.geometry import ScanGeometry
from bubsub.core.projection.mesh import Polygon
from bubsub.clients.pipeline.inputs.sides import (LOCAL_VIEWS, TRUNCATED_VIEWS, check_lateral_truncation,
                                                  side_bubble_signal, side_signal)
from bubsub.clients.pipeline.inputs.fov import field_of_view

C = -0.1


def _old_rule_hits(scan):
    """Projections in which the sample's data (liquid included) stand above the air level at a side."""
    left, right, level = side_signal(scan.data)
    return max(int(np.count_nonzero(left > level)), int(np.count_nonzero(right > level)))


@pytest.fixture(scope="module")
def raw_scan(tmp_path_factory):
    """A raw phase-contrast scan (flats, darks, 16 keV, 300 mm, axis 5.3 px off centre) of a liquid cylinder
    9 binned pixels inside each side of the axis-centred crop, prepared with --bin 2 --delta-beta 1450
    --center auto --background auto."""
    from bubsub.core.prep import prepare, prepare_options

    out = tmp_path_factory.mktemp("raw")
    cols, px, off = 240, 0.006, 5.3
    axis = cols / 2 - 0.5 + off
    crop = int(2 * min(axis + 0.5, cols - 0.5 - axis)) // 2 * 2  # the columns prepare keeps, raw
    radius = (crop / 4 - 9) * 2 * px
    s = raw_settings(seed=1, n_angles=60, cols=cols, rows=2, pixel_size=px, axis_offset=off, distance=300.0,
                     container_radius=radius, wall=0.0, supersample=2)
    write_raw_simulation(out, disc_foam(1, radius, n_bubbles=12, radius_range=(0.1 * radius, 0.22 * radius)), s)
    report = prepare(out / "raw.h5", out / "scan.h5",
                     prepare_options(roi="1:2,:", bin=2, delta_beta=1450, center="auto", background="auto"),
                     progress=False)
    return out, report, s


def test_a_raw_scan_whose_liquid_blurs_into_the_sides_passes_and_reconstructs(raw_scan):
    from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir
    from bubsub.clients.pipeline.results.outputs import write_outputs
    from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct

    out, report, s = raw_scan
    # air at the sides: the pixel gains are not taken (--double-flat auto), the scan prepared as without that step
    assert "double_flat_field" not in {st["step"] for st in report["steps"]}
    centre = next(st for st in report["steps"] if st["step"] == "center")["axis_column_raw"]
    assert centre == pytest.approx(s.axis_column, abs=1.0)
    scan = read_scan(out / "scan.h5")
    assert _old_rule_hits(scan) >= TRUNCATED_VIEWS * scan.n_angles  # the liquid's edge does reach the sides
    assert check_lateral_truncation(scan) is None  # but no bubble does: no refusal, no warning
    rec = reconstruct(scan, ReconstructionSettings(progress=False))  # the defaults, as bubsub reconstruct
    write_outputs(out / "rec", rec, scan_path=out / "scan.h5")
    res = evaluate_dir(out / "rec", out)
    # every bubble found and none spurious in the field of view (a fitted bubble wholly beyond it, in the
    # preview's extension, is neither)
    assert res["matching"]["found"] == res["bubbles_truth"] >= 4 and res["matching"]["spurious"] == 0
    assert res["ddi"] <= 0.05


def _cone_box_scan(inside=True):
    """A cone-beam scan (24 views over 360 degrees, 40 x 20 detector) of a liquid box whose corners leave the
    field of view at diagonal angles, the box's exact projection as background, two balls of gas."""
    g = ScanGeometry.cone(np.linspace(0, 2 * np.pi, 24, endpoint=False), source_origin=20.0, origin_detector=20.0,
                          pixel_size=0.1, cols=40, rows=20)
    r, hz = field_of_view(g)
    background = MeshProjector(g).forward([liquid_box((1.7 * r, 1.7 * r, 4 * hz), 0.1)])
    x = 0.3 * r if inside else 1.05 * r
    balls = [sphere_mesh((x, 0.2 * r, 0.1 * hz), 0.25 * r, C, 3), sphere_mesh((-0.3 * r, -0.3 * r, 0.0), 0.2 * r, C, 3)]
    noise = np.random.default_rng(2).normal(0, 0.003, background.shape)
    data = background + MeshProjector(g).forward(balls) + noise
    return Scan(data=data.astype(np.float32), geometry=g, background=background.astype(np.float32),
                bubble_contrast=C)


def test_a_cone_scan_whose_background_holds_its_liquid_box_passes():
    scan = _cone_box_scan()
    assert _old_rule_hits(scan) >= LOCAL_VIEWS * scan.n_angles  # the box's corners reach the sides
    assert check_lateral_truncation(scan) is None


def _wide_column(radius_over_fov, seed=0, bubbles=40, angles=24, cols=48, within=None):
    """A 2D parallel scan of a liquid disc ``radius_over_fov`` times the field of view's radius filled with gas
    discs out to its wall (or to ``within`` times the field of view's radius), its exact projection as
    background."""
    g = ScanGeometry.parallel(np.linspace(0, np.pi, angles, endpoint=False), pixel_size=0.05, cols=cols)
    fov = field_of_view(g)[0]
    radius = radius_over_fov * fov
    reach = radius if within is None else within * fov
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    discs = []
    while len(discs) < bubbles:
        c, q = rng.uniform(-radius, radius, 2), rng.uniform(0.08, 0.16) * fov
        if np.hypot(*c) + q < reach and all(np.hypot(*(c - d)) > q + e for d, e in discs):
            discs.append((c, q))
    gas = [Polygon(c + q * np.stack([np.cos(t), np.sin(t)], 1), C) for c, q in discs]
    ring = Polygon(radius * np.stack([np.cos(t), np.sin(t)], 1) / np.cos(np.pi / 48), 0.1)  # circumscribed
    projector = MeshProjector(g, supersampling=2)
    background = projector.forward([ring])
    data = background + projector.forward(gas) + rng.normal(0, 0.002, background.shape)
    return Scan(data=data.astype(np.float32), geometry=g, background=background.astype(np.float32),
                bubble_contrast=C), discs, fov


def test_a_foam_wider_than_the_detector_is_named_local_tomography_in_one_line(caplog):
    scan, _, _ = _wide_column(1.5)
    left, right, level = side_bubble_signal(scan.bubble_data, C)
    assert max(np.count_nonzero(left > level), np.count_nonzero(right > level)) >= LOCAL_VIEWS * scan.n_angles
    with caplog.at_level(logging.WARNING, logger="bubsub"):
        text = check_lateral_truncation(scan)
    assert [r.getMessage() for r in caplog.records] == [text]
    assert text.startswith("note: the scan is local tomography (the foam is wider than the detector): the bubbles' "
                           "signal (data - background) reaches the detector's left side in ") and "\n" not in text


def test_a_foam_within_the_field_of_view_in_a_wider_liquid_passes():
    # the liquid 1.5 times the field of view's radius, its bubbles within 0.8 of it: the background holds the rest
    scan, _, _ = _wide_column(1.5, bubbles=8, within=0.8)
    assert _old_rule_hits(scan) == scan.n_angles
    assert check_lateral_truncation(scan) is None


def test_bubbles_at_one_side_in_a_few_projections_warn_in_one_line_and_pass(caplog):
    scan = _cone_box_scan(inside=False)  # one ball half outside the field of view
    left, right, level = side_bubble_signal(scan.bubble_data, C)
    seen = max(np.count_nonzero(left > level), np.count_nonzero(right > level))
    assert TRUNCATED_VIEWS * scan.n_angles <= seen < LOCAL_VIEWS * scan.n_angles
    with caplog.at_level(logging.WARNING, logger="bubsub"):
        text = check_lateral_truncation(scan)
        assert check_lateral_truncation(scan) == text  # the command line and reconstruct both check: one line
    assert [r.getMessage() for r in caplog.records] == [text]
    assert text.startswith("warning: the scan: the bubbles' signal") and "\n" not in text


def test_a_whole_projection_offset_drifting_with_the_beam_is_not_a_bubble_at_the_sides():
    # bubbles' signal zero at the sides; each projection offset by a drift from -0.2 to +0.2 of the signal's peak
    # (a flat-field correction that follows the beam's decay imperfectly)
    views, cols = 60, 64
    values = np.zeros((views, cols))
    values[:, 16:48] = 1.0
    drift = np.linspace(-0.2, 0.2, views)[:, None] + np.random.default_rng(0).normal(0, 0.01, (views, cols))
    left, right, level = side_bubble_signal(-(values + drift), C)
    assert np.count_nonzero(left > level) == np.count_nonzero(right > level) == 0
    # the same signal at the sides in the last third of the projections is seen there
    values[40:, :3] = 0.6
    left, _, level = side_bubble_signal(-(values + drift), C)
    assert np.count_nonzero(left > level) >= 18
