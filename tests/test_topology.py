"""Few-view robustness: blob detection, the box-constrained preview, topology changes, dense foams."""

import numpy as np
import pytest

from bubsub.clients.pipeline.regions.local import scene_residual
from bubsub.clients.pipeline.static.blobs import log_blobs
from bubsub.clients.pipeline.static.preview import voxel_preview
from bubsub.clients.pipeline.static.topology import adapt_topology
from bubsub.core import MeshProjector, ScanGeometry, circle_surface
from bubsub.core.foam.dense import dense_foam2d, dense_foam3d
from bubsub.core.projection.validity import check_bubbles
from bubsub.core.projection.masks import rasterize

MU = -0.1


def _disc_image(centres, radii, n=96, half=3.0):
    extent = (-half, half, -half, half)
    items = [circle_surface(c, r, MU, control=32, levels=3).fine() for c, r in zip(centres, radii)]
    return -rasterize(items, (n, n), extent), extent  # bubbles positive, |contrast| inside


def test_log_blobs_finds_touching_discs_of_different_sizes_with_their_radii():
    centres = np.array([[-1.0, 0.0], [0.45, 0.0], [1.6, 1.6], [-1.5, -1.8]])
    radii = np.array([0.8, 0.6, 0.35, 0.5])  # the first two touch (gap 0.05 mm)
    image, extent = _disc_image(centres, radii)
    found, r = log_blobs(image, extent, MU, min_radius=0.2, max_radius=1.2)
    assert len(found) == 4
    dist = np.linalg.norm(found[:, None] - centres[None], axis=2)
    match = dist.argmin(axis=1)
    assert sorted(match) == [0, 1, 2, 3]
    assert np.all(dist.min(axis=1) < 0.15)
    assert r == pytest.approx(radii[match], rel=0.25)


@pytest.mark.parametrize("ndim", [2, 3])
def test_parallel_scale_space_finds_exactly_scikit_images_blobs(ndim):
    # log_blobs computes blob_log's scale space itself, one scale per thread: same scales, same peaks
    from skimage.feature import blob_log

    from bubsub.clients.pipeline.static.blobs import _blob_log

    rng = np.random.default_rng(4)
    shape = (40, 48, 44)[:ndim]
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)
    img = rng.normal(0, 0.02, shape)
    for _ in range(6):
        c, r = rng.uniform(5, np.array(shape) - 5), rng.uniform(2, 6)
        img += np.linalg.norm(grid - c, axis=-1) < r
    peaks, sigmas, strength = _blob_log(img, 1.0, 5.0, 9, 0.1)
    ref = blob_log(img, min_sigma=1.0, max_sigma=5.0, num_sigma=9, threshold=0.1, overlap=1.0, exclude_border=False)
    assert len(peaks) >= 6
    np.testing.assert_array_equal(peaks[:, :ndim], ref[:, :ndim])
    np.testing.assert_array_equal(sigmas[peaks[:, ndim]], ref[:, ndim])
    from scipy import ndimage

    # the strength is the scale-normalised response at each peak, highest first
    expected = [-sigmas[s] ** 2 * ndimage.gaussian_laplace(img, sigmas[s])[tuple(p)]
                for p, s in zip(peaks[:, :ndim], peaks[:, ndim])]
    np.testing.assert_allclose(strength, expected, atol=1e-12)
    assert np.all(np.diff(strength) <= 0)


def _scan(truth, n_angles=10, cols=128):
    geometry = ScanGeometry.parallel(np.linspace(0, np.pi, n_angles, endpoint=False), cols=cols, pixel_size=0.05)
    return geometry, MeshProjector(geometry).forward(truth)


def test_box_preview_stays_in_bounds_and_separates_touching_bubbles():
    truth = [circle_surface([-0.75, 0.0], 0.7, MU, control=32, levels=3),
             circle_surface([0.7, 0.0], 0.65, MU, control=32, levels=3)]
    geometry, data = _scan(truth, n_angles=8)
    image, extent = voxel_preview(data, geometry, MU, voxel_size=0.05, method="box")
    assert image.min() >= 0 and image.max() <= 0.1 + 1e-6
    found, _ = log_blobs(image, extent, MU, min_radius=0.3, max_radius=1.0)
    assert len(found) == 2
    with pytest.raises(ValueError, match="preview method"):
        voxel_preview(data, geometry, MU, method="fbp")


def _adapt(start, data, geometry, **kw):
    def preview(p):
        return voxel_preview(p, geometry, MU, voxel_size=0.05)

    return adapt_topology(MeshProjector(geometry), start, data, preview=preview,
                          new_bubble=lambda c, r: circle_surface(c, r, MU), min_radius=0.15, max_radius=1.0,
                          rounds=2, iterations=15, touch=0.1, **kw)


def test_topology_adds_the_missed_bubble_and_removes_the_spurious_one():
    truth = [circle_surface([-1.0, 0.5], 0.6, MU, control=32, levels=3),
             circle_surface([1.0, -0.5], 0.5, MU, control=32, levels=3)]
    geometry, data = _scan(truth)
    start = [circle_surface([-1.0, 0.5], 0.6, MU), circle_surface([0.5, 1.8], 0.3, MU)]  # one missed, one spurious
    projector = MeshProjector(geometry)
    f0 = projector.objective(start, data)[0]
    kept, summary = _adapt(start, data, geometry, steps=("remove", "add"))
    kinds = [c["change"] for c in summary["changes"]]
    assert kinds.count("remove") == 1 and kinds.count("add") == 1
    assert len(kept) == 2 and summary["objective"] < 0.05 * f0
    centres = np.array(sorted(tuple(s.fine().centroid) for s in kept))
    assert np.allclose(centres, [(-1.0, 0.5), (1.0, -0.5)], atol=0.1)
    for c in summary["changes"]:
        assert c["objective_after"] < c["objective_before"] or c["change"] == "remove"


def test_a_residual_given_is_kept_up_to_date_through_the_rounds():
    # two rounds (an add, then a look that finds nothing more), each started from the residual the last kept
    truth = [circle_surface([-1.0, 0.5], 0.6, MU, control=32, levels=3),
             circle_surface([1.0, -0.5], 0.5, MU, control=32, levels=3)]
    geometry, data = _scan(truth)
    start = [circle_surface([-1.0, 0.5], 0.6, MU), circle_surface([0.5, 1.8], 0.3, MU)]
    projector = MeshProjector(geometry)
    residual = scene_residual(projector, start, data)
    kept, summary = _adapt(start, data, geometry, steps=("remove", "add"), residual=residual)
    assert summary["rounds"] == 2 and len(kept) == 2
    fresh = scene_residual(projector, kept, data)
    np.testing.assert_allclose(residual, fresh, atol=1e-6 * np.abs(data).max())  # float32 projections
    assert summary["objective"] == pytest.approx(0.5 * float(np.vdot(fresh, fresh)), rel=1e-6)
    again, summary_again = _adapt(start, data, geometry, steps=("remove", "add"))  # the residual projected
    assert summary_again["objective"] == pytest.approx(summary["objective"], rel=1e-6)


def test_a_round_that_only_removed_bubbles_ends_the_rounds_when_asked():
    truth = [circle_surface([-1.0, 0.5], 0.6, MU, control=32, levels=3)]
    geometry, data = _scan(truth)
    start = [circle_surface([-1.0, 0.5], 0.6, MU), circle_surface([0.5, 1.8], 0.3, MU)]  # one spurious
    calls = []

    def counted(p):
        calls.append(1)
        return voxel_preview(p, geometry, MU, voxel_size=0.05)

    def adapt(**kw):
        calls.clear()
        kept, summary = adapt_topology(MeshProjector(geometry), start, data, preview=counted,
                                       new_bubble=lambda c, r: circle_surface(c, r, MU), min_radius=0.15,
                                       max_radius=1.0, rounds=2, iterations=15, steps=("remove", "add"), **kw)
        return kept, summary, len(calls)

    kept, summary, previews = adapt(after_removals=False)
    assert [c["change"] for c in summary["changes"]] == ["remove"] and len(kept) == 1
    assert summary["rounds"] == 1 and previews == 1
    kept, summary, previews = adapt()  # the default: a second round looks again, and finds nothing
    assert [c["change"] for c in summary["changes"]] == ["remove"] and len(kept) == 1
    assert summary["rounds"] == 2 and previews == 2


def test_topology_splits_a_bubble_that_covers_two():
    truth = [circle_surface([-0.6, 0.0], 0.55, MU, control=32, levels=3),
             circle_surface([0.6, 0.0], 0.55, MU, control=32, levels=3)]
    geometry, data = _scan(truth)
    start = [circle_surface([0.0, 0.0], 0.8, MU)]
    stretched = start[0].with_vertices(start[0].vertices * [1.6, 0.7])
    kept, summary = _adapt([stretched], data, geometry, steps=("split",))
    assert [c["change"] for c in summary["changes"]] == ["split"]
    assert len(kept) == 2 and check_bubbles(kept) == []


def test_a_bubble_holding_two_preview_blobs_is_tried_before_an_elongated_one():
    # an elongated true bubble (axis ratio 2, one bubble: its split is rejected) and a round bubble that covers
    # two true discs; with one try, the split that the preview's two blobs call for must be the one tried
    ellipse = circle_surface([-1.3, 0.0], 0.5, MU, control=32, levels=3)
    ellipse = ellipse.with_vertices((ellipse.vertices - [-1.3, 0.0]) * [1.0, 0.5] + [-1.3, 0.0])
    truth = [ellipse, circle_surface([1.0, -0.52], 0.45, MU, control=32, levels=3),
             circle_surface([1.0, 0.52], 0.45, MU, control=32, levels=3)]
    geometry, data = _scan(truth, n_angles=16)
    image = voxel_preview(data, geometry, MU, voxel_size=0.05)
    start = [ellipse, circle_surface([1.0, 0.0], 0.8, MU)]
    kept, summary = _adapt(start, data, geometry, steps=("split",), image=image, max_tries=1)
    splits = [c for c in summary["changes"] if c["change"] == "split"]
    assert splits and np.allclose(splits[0]["centre"], [1.0, 0.0], atol=0.1)
    assert len(kept) == 3 and check_bubbles(kept) == []


def test_topology_merges_two_halves_of_one_bubble_and_leaves_a_good_fit_alone():
    truth = [circle_surface([0.0, 0.0], 0.8, MU, control=32, levels=3)]
    geometry, data = _scan(truth)
    halves = [circle_surface([-0.42, 0.0], 0.4, MU), circle_surface([0.42, 0.0], 0.4, MU)]
    kept, summary = _adapt(halves, data, geometry, steps=("merge",))
    assert [c["change"] for c in summary["changes"]] == ["merge"] and len(kept) == 1
    again, summary = _adapt(kept, data, geometry)
    assert summary["changes"] == [] and len(again) == 1


def test_a_merge_and_a_split_keep_the_residual_and_the_footprints_of_the_new_bubbles():
    """merge_step and split_step add the new bubbles' own projections (on windows around them) to the
    residual: afterwards it is the new scene's Proj - d, and each kept footprint the new bubble's own."""
    from bubsub.clients.pipeline.regions.local import Footprints, scene_residual
    from bubsub.clients.pipeline.static.topology import merge_step, split_step

    truth = [circle_surface([0.0, 0.0], 0.8, MU, control=32, levels=3),
             circle_surface([-1.5, -1.6], 0.4, MU, control=32, levels=3),
             circle_surface([1.6, 1.5], 0.4, MU, control=32, levels=3)]
    geometry, data = _scan(truth)
    projector = MeshProjector(geometry)
    others = [circle_surface([-1.5, -1.6], 0.4, MU), circle_surface([1.6, 1.5], 0.4, MU)]
    halves = [circle_surface([-0.42, 0.0], 0.4, MU), circle_surface([0.42, 0.0], 0.4, MU)] + others
    stretched = circle_surface([0.0, 0.0], 0.8, MU)
    stretched = [stretched.with_vertices(stretched.vertices * [1.6, 0.7])] + others
    new = lambda c, r: circle_surface(c, r, MU)  # noqa: E731
    # a split of the stretched bubble is the two true halves of the merge test, set apart
    truth_two = [circle_surface([-0.6, 0.0], 0.55, MU, control=32, levels=3),
                 circle_surface([0.6, 0.0], 0.55, MU, control=32, levels=3)] + truth[1:]
    data_two = projector.forward(truth_two)
    for step, start, d, kw in ((merge_step, halves, data, dict(touch=0.1)),
                               (split_step, stretched, data_two, dict(ratio=1.6))):
        residual, own, changes = scene_residual(projector, start, d), Footprints(projector, start), []
        out, own = step(projector, start, residual, own, d, new, changes, 0, iterations=15, max_tries=4, **kw)
        assert len(changes) == 1 and len(out) == len(start) + (1 if step is split_step else -1)
        # to float32 rounding: the residual sums bubbles' projections rounded one by one, the scene's rounds the sum
        np.testing.assert_allclose(residual, scene_residual(projector, out, d), rtol=0, atol=1e-6)
        for k, s in enumerate(out):
            np.testing.assert_allclose(own[k].values.sum(), projector.forward([s]).astype(np.float64).sum(),
                                       rtol=1e-12)


@pytest.mark.parametrize("make, ndim", [(dense_foam2d, 2), (dense_foam3d, 3)])
def test_dense_foam_is_dense_disjoint_and_keeps_its_films(make, ndim):
    kw = {"n_bubbles": 12, "size": 5.0} if ndim == 2 else {"n_bubbles": 8, "size": (5.0, 5.0, 3.0), "subdivisions": 2,
                                                            "film": 0.1, "border": 0.1, "margin": 0.1}
    ph = make(3, **kw)
    assert 0.6 <= ph.gas_fraction <= 0.85
    assert check_bubbles(ph.bubbles, surfaces=("fine",)) == []
    film = kw.get("film", 0.08)
    # the closest neighbours are a film apart, not more (pressed together) and not less (disjoint)
    gaps = []
    for i, a in enumerate(ph.bubbles):
        d = [np.min(np.linalg.norm(a.vertices[:, None] - b.vertices[None], axis=2))
             for j, b in enumerate(ph.bubbles) if j != i]
        gaps.append(min(d))
    assert min(gaps) >= film - 1e-9
    assert np.median(gaps) < 1.5 * film
    assert make(3, **kw).bubbles[0].vertices.tolist() == ph.bubbles[0].vertices.tolist()  # seeded


def test_footprint_matches_the_dense_projection_it_replaces():
    from bubsub.clients.pipeline.regions.local import Footprint, others_removed

    rng = np.random.default_rng(3)
    p = np.zeros((5, 7, 9), np.float32)
    p[1:3, 2:5, 4:8] = rng.random((2, 3, 4))
    q = np.zeros_like(p)
    q[2:4, 1:3, 1:3] = rng.random((2, 2, 2))
    residual = rng.standard_normal(p.shape)
    fp, fq = Footprint(p), Footprint(q)
    assert len(fp.index) == 24  # only the support is stored
    dense_gain = 0.5 * np.sum((residual - p) ** 2) - 0.5 * np.sum(residual ** 2)
    assert fp.removal_gain(residual) == pytest.approx(dense_gain, rel=1e-12)
    dense_gain = 0.5 * np.sum((residual + p) ** 2) - 0.5 * np.sum(residual ** 2)
    assert fp.addition_gain(residual) == pytest.approx(dense_gain, rel=1e-12)
    per_view = 0.5 * ((residual - p) ** 2 - residual ** 2).reshape(len(residual), -1).sum(axis=1)
    np.testing.assert_allclose(fp.removal_gains(residual), per_view, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(others_removed(residual, fp, fq), p + q - residual, rtol=0, atol=1e-12)
    r = residual.copy()
    fp.add_to(r, -1.0)
    np.testing.assert_allclose(r, residual - p, rtol=0, atol=1e-12)


@pytest.mark.parametrize("ndim", [2, 3])
def test_window_footprints_and_local_fits_match_the_whole_detector(ndim):
    """A bubble's own projection through a detector window around its shadow is its whole-detector
    projection; local fits on one window rank candidates as the whole detector does."""
    from bubsub.core import MeshProjector, ScanGeometry, circle_surface, sphere_surface
    from bubsub.clients.pipeline.regions.local import Footprint, Window, local_fits

    angles = np.linspace(0, np.pi, 6, endpoint=False)
    if ndim == 3:
        g = ScanGeometry.cone(angles, source_origin=60.0, origin_detector=10.0, pixel_size=0.05, cols=96, rows=64)
        make = sphere_surface
        centres = ([0.5, 0.2, 0.1], [-0.9, -0.3, 0.0])
    else:
        g = ScanGeometry.parallel(angles, pixel_size=0.05, cols=128)
        make = circle_surface
        centres = ([0.5, 0.2], [-0.9, -0.3])
    P = MeshProjector(g)
    s = make(centres[0], 0.4, -0.2)
    window = Window(P, [s])
    assert window.starts is not None and np.prod(window.size[-1]) < g.det_cols  # smaller than the detector
    fw, ff = window.footprint(s), Footprint(P.forward([s]))
    np.testing.assert_array_equal(fw.index, ff.index)
    np.testing.assert_allclose(fw.values, ff.values, atol=1e-6)
    # data: one bubble at the first centre, a little larger; candidates: the right one vs. a wrong one
    target = P.forward([make(centres[0], 0.45, -0.2)]).astype(np.float64)
    (right, f_right), (_, f_wrong) = local_fits(P, [[s], [make(np.add(centres[0], 0.15), 0.3, -0.2)]], target, 10)
    assert f_right < f_wrong
    # the target is zero off the window, and the fitted bubble's shadow stays inside it: the same objective
    assert f_right == pytest.approx(P.objective(right, target)[0], rel=1e-6)


def test_auto_initialisation_keeps_the_candidate_set_that_fits_the_data_best():
    from bubsub.clients.pipeline.static.initial import choose_initial

    centres = np.array([[-0.65, 0.0], [0.67, 0.0], [0.2, 1.8]])
    truth = [circle_surface(c, r, MU, control=32, levels=3) for c, r in zip(centres, [0.65, 0.65, 0.5])]
    image, extent = _disc_image(centres, [0.65, 0.65, 0.5])
    from scipy import ndimage

    image = ndimage.gaussian_filter(image, 3.0)  # a few-view preview's blur: the two big discs run together
    geometry, data = _scan(truth)
    projector = MeshProjector(geometry)
    surfaces, summary = choose_initial(image, extent, MU, projector, data)
    chosen = summary["detector"]
    assert set(summary) == {"log", "dt", "detector"}
    assert summary[chosen]["score"] == min(summary["log"]["score"], summary["dt"]["score"])
    assert projector.objective(surfaces, data)[0] == pytest.approx(summary[chosen]["objective"])
    found = np.array([s.fine().centroid for s in surfaces])
    assert len(found) == 3 and np.all(np.linalg.norm(found[:, None] - centres[None], axis=2).min(axis=0) < 0.15)
    with pytest.raises(ValueError, match="detector"):
        choose_initial(image, extent, MU, projector, data, detector="otsu")


def test_bubble_diagnosis_counts_centres_and_finds_merged_bubbles():
    from bubsub.bench.bubbles import count_centres, per_bubble

    extent = (-3.0, 3.0, -3.0, 3.0)
    truth = [circle_surface(c, 0.5, MU, control=32, levels=3).fine() for c in ([-1.5, 0], [-0.4, 0], [1.5, 1.5])]
    from bubsub.core.projection.masks import label_image

    labels = label_image(truth, (96, 96), extent)
    centres = [[-1.5, 0.0], [1.4, 1.5], [1.6, 1.5], [2.5, -2.5]]  # one in 1, none in 2, two in 3, one in liquid
    assert count_centres(labels, centres, extent) == (1, 1, 1, 1)
    # one reconstructed region over the first two bubbles, one over the third
    rec = label_image([circle_surface([-0.95, 0], 1.1, MU).fine(), truth[2]], (96, 96), extent)
    rows, owner = per_bubble(labels, rec)
    assert [r[4] for r in rows] == [[1, 2], [1, 2], []]
    assert rows[2][3] == pytest.approx(0.0) and 0.3 < rows[0][3] < 0.8


@pytest.mark.parametrize("ndim", [2, 3])
def test_inside_matches_the_winding_number_of_every_point(ndim):
    """The split step's point test: points outside the bounding box are skipped, and the answer is
    still the one-point coverage of every point (near the surface, inside, far away)."""
    from bubsub.clients.pipeline.static.topology import points_inside
    from bubsub.core import sphere_surface
    from bubsub.core.projection.masks import coverage

    centre = np.array([0.3, -0.2, 0.1][:ndim])
    s = (circle_surface(centre, 1.0, 0.1) if ndim == 2 else sphere_surface(centre, 1.0, 0.1)).fine()
    rng = np.random.default_rng(4)
    d = rng.normal(size=(200, ndim))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    radii = np.concatenate([rng.uniform(0, 3, 150), np.full(50, 0.99)])  # a band just inside the fine surface
    points = centre + d * radii[:, None]
    tiny = 1e-6
    truth = [coverage(s, (1,) * ndim, tuple(np.stack([p - tiny, p + tiny], 1).ravel())).item() > 0 for p in points]
    got = points_inside(s, points)
    assert got.dtype == bool and got.tolist() == truth
    assert 0 < got.sum() < len(points)


def test_a_later_round_tries_removals_only_among_the_bubbles_the_last_refit_moved(monkeypatch):
    from bubsub.clients.pipeline.static import topology

    # two far-apart good bubbles and a spurious one: round 1 removes it and refits no one (nothing touches it);
    # a missed bubble is added, refitted, and round 2 weighs the removal of that one only
    truth = [circle_surface([-1.5, 0.5], 0.5, MU, control=32, levels=3),
             circle_surface([1.5, -0.5], 0.5, MU, control=32, levels=3),
             circle_surface([0.0, -1.6], 0.4, MU, control=32, levels=3)]
    geometry, data = _scan(truth)
    start = [circle_surface([-1.5, 0.5], 0.5, MU), circle_surface([1.5, -0.5], 0.5, MU),
             circle_surface([0.3, 1.8], 0.3, MU)]
    weighed = []
    real = topology.remove_step

    def spy(surfaces, residual, own, changes, round_no, cost=0.0, only=None):
        weighed.append(len(surfaces) if only is None else len(only))
        return real(surfaces, residual, own, changes, round_no, cost, only=only)

    monkeypatch.setattr(topology, "remove_step", spy)
    kept, summary = _adapt(start, data, geometry, steps=("remove", "add"))
    assert [c["change"] for c in summary["changes"] if c["round"] == 0] == ["remove", "add"]
    assert summary["rounds"] == 2 and weighed[0] == 3
    # round 2: only the bubbles round 1's refit moved (the added one and its neighbours), not all three
    assert weighed[1] == summary["refits"][0]["bubbles"] < len(kept) == 3


def _spheroid(centre, axes):
    from bubsub.core import sphere_surface

    s = sphere_surface((0.0, 0.0, 0.0), 1.0, MU, control=162, levels=1)
    return s.with_vertices(np.asarray(s.vertices) * np.asarray(axes) + np.asarray(centre))


def test_a_cut_bubble_is_called_elongated_by_its_part_in_view_across_the_edge_plane():
    from bubsub.clients.pipeline.static.topology import split_axis

    angles = np.linspace(0, np.pi, 12, endpoint=False)
    geometry = ScanGeometry.parallel(angles, pixel_size=0.05, cols=64, rows=32)
    top = 0.8  # the detector's top edge plane (16 rows of 0.05 mm above the axis)
    # a flat bubble beyond the top edge whose round cap is all the data see: no split candidate, where its whole
    # surface (axis ratio 3) was one
    flat = _spheroid((0.0, 0.0, top + 0.05), (0.6, 0.6, 0.2))
    c, ratio, axis = split_axis(flat, ScanGeometry.parallel(angles, pixel_size=0.05, cols=64, rows=64))
    assert ratio == pytest.approx(3.0, rel=0.05)  # wholly in view on a taller detector: as before
    c, ratio, axis = split_axis(flat, geometry)
    assert ratio < 1.1
    # a cap longer than wide along the plane (two caps one bubble holds): elongated along x
    long = _spheroid((0.0, 0.0, top + 0.1), (0.8, 0.3, 0.3))
    c, ratio, axis = split_axis(long, geometry)
    assert ratio > 2.0
    assert abs(axis[0]) > 0.95 * np.linalg.norm(axis)
    # a bubble swollen upright into the top edge plane: its part in view is elongated upright
    swollen = _spheroid((0.0, 0.0, 0.3), (0.25, 0.25, 0.7))
    c, ratio, axis = split_axis(swollen, geometry)
    assert ratio > 1.6 and abs(axis[2]) > 0.95 * np.linalg.norm(axis)
    # a bubble in view is measured whole: the long axis of an upright spheroid is vertical
    upright = _spheroid((0.0, 0.0, 0.0), (0.2, 0.2, 0.5))
    c, ratio, axis = split_axis(upright, geometry)
    assert ratio == pytest.approx(2.5, rel=0.05) and abs(axis[2]) > 0.99 * np.linalg.norm(axis)
    np.testing.assert_allclose(c, 0.0, atol=1e-9)
