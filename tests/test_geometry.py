import numpy as np
import pytest

from bubsub.core import ScanGeometry

astra = pytest.importorskip("astra")


def random_angles(rng, n=None):
    n = n or int(rng.integers(1, 12))
    return np.sort(rng.uniform(0, 2 * np.pi, n))


@pytest.mark.parametrize("trial", range(5))
def test_circular_factories_match_astra_geom_2vec(rng, trial):
    ang = random_angles(rng)
    px, py = rng.uniform(0.01, 2, 2)
    rows, cols = (int(x) for x in rng.integers(1, 64, 2))
    so, od = rng.uniform(10, 1000), rng.uniform(-5, 500)
    cases = [
        (ScanGeometry.parallel(ang, pixel_size=px, cols=cols), astra.create_proj_geom("parallel", px, cols, ang)),
        (ScanGeometry.cone(ang, source_origin=so, origin_detector=od, pixel_size=px, cols=cols),
         astra.create_proj_geom("fanflat", px, cols, ang, so, od)),
        (ScanGeometry.parallel(ang, pixel_size=(px, py), cols=cols, rows=rows),
         astra.create_proj_geom("parallel3d", px, py, rows, cols, ang)),
        (ScanGeometry.cone(ang, source_origin=so, origin_detector=od, pixel_size=(px, py), cols=cols, rows=rows),
         astra.create_proj_geom("cone", px, py, rows, cols, ang, so, od)),
    ]
    for ours, theirs in cases:
        vec = astra.geom_2vec(theirs)
        assert ours.kind == vec["type"]
        np.testing.assert_allclose(ours.vectors, vec["Vectors"], atol=1e-12)
        assert ScanGeometry.from_astra(vec) == ours
        back = ours.to_astra()
        assert back["type"] == vec["type"]
        for key in ("DetectorCount", "DetectorRowCount", "DetectorColCount"):
            assert back.get(key) == vec.get(key)


def test_shapes_and_slicing(rng):
    ang = random_angles(rng, 10)
    g3 = ScanGeometry.cone(ang, source_origin=300, origin_detector=15, pixel_size=0.1, cols=7, rows=5)
    assert g3.shape == (10, 5, 7) and g3.ndim == 3 and g3.is_cone
    g2 = ScanGeometry.parallel(ang, pixel_size=0.1, cols=9)
    assert g2.shape == (10, 9) and g2.ndim == 2 and g2.det_rows is None and g2.det_count == 9
    even = g3[::2]
    assert even.n_angles == 5
    np.testing.assert_array_equal(even.vectors, g3.vectors[::2])
    assert g3[3].shape == (1, 5, 7)
    with pytest.raises(IndexError):
        g3[10:]


def test_vectors_are_immutable():
    g = ScanGeometry.parallel([0.0, 1.0], pixel_size=1, cols=4)
    with pytest.raises(ValueError):
        g.vectors[0, 0] = 5


def test_repr_reads_as_the_call_that_made_it(rng):
    import numpy as np  # noqa: F401 - used by eval

    ang = np.linspace(0, np.pi, 5, endpoint=False)
    for g in (
        ScanGeometry.parallel(ang, pixel_size=0.5, cols=8),
        ScanGeometry.cone(ang, source_origin=300.0, origin_detector=15.0, pixel_size=0.06, cols=8, rows=4),
    ):
        again = eval(repr(g), {"np": np, "ScanGeometry": ScanGeometry})
        np.testing.assert_allclose(again.vectors, g.vectors, atol=1e-12)
        assert again.shape == g.shape


def test_pixel_centre_convention():
    # pixel (r, c) centre = d + (c - cols/2 + 0.5) u + (r - rows/2 + 0.5) v
    vec = np.array([[0, 0, 1, 1, 2, 3, 0.5, 0, 0, 0, 0.25, 0]])
    g = ScanGeometry.from_astra("parallel3d_vec", vec, det_rows=3, det_cols=4)
    centres = g.pixel_centres()
    assert centres.shape == (1, 3, 4, 3)
    r, c = 2, 1
    expected = np.array([1, 2, 3]) + (c - 2 + 0.5) * np.array([0.5, 0, 0]) + (r - 1.5 + 0.5) * np.array([0, 0.25, 0])
    np.testing.assert_allclose(centres[0, r, c], expected)


def test_rays_are_unit_and_point_from_source(rng):
    g = ScanGeometry.cone(random_angles(rng, 3), source_origin=100, origin_detector=50, pixel_size=1, cols=5, rows=4)
    o, d = g.rays(supersampling=2)
    assert o.shape == (3, 4, 5, 4, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    # the ray from the source reaches the detector plane in the pixel
    centres = g.pixel_centres()
    to_pixel = centres[..., None, :] - o
    assert np.all(np.einsum("...i,...i", to_pixel, d) > 0)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(kind="cone_vec", vectors=np.zeros((3, 6)), det_rows=2, det_cols=2), "shape"),
        (dict(kind="cone_vec", vectors=np.full((3, 12), np.nan), det_rows=2, det_cols=2), "NaN"),
        (dict(kind="fan", vectors=np.ones((3, 6)), det_count=3), "unknown geometry kind"),
        (dict(kind="cone_vec", vectors=np.ones((3, 12)), det_rows=0, det_cols=2), "det_rows"),
        (dict(kind="parallel_vec", vectors=np.ones((3, 6)), det_rows=2, det_cols=2), "det_count"),
    ],
)
def test_bad_geometry_is_refused_clearly(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ScanGeometry.from_astra(**kwargs)


@pytest.mark.parametrize("kind", ["cone", "parallel", "fan"])
def test_a_detector_window_projects_what_the_whole_detector_shows_there(kind):
    from bubsub.core import MeshProjector, circle_surface, sphere_surface

    angles = np.linspace(0, np.pi, 5, endpoint=False)
    if kind == "fan":
        g = ScanGeometry.cone(angles, source_origin=40.0, origin_detector=10.0, pixel_size=0.05, cols=64)
        item = circle_surface([0.2, -0.1], 0.6, -0.3)
        r0, c0, rows, cols = 0, np.array([3, 10, 20, 0, 30]), None, 34
    else:
        g = (ScanGeometry.cone(angles, source_origin=40.0, origin_detector=10.0, pixel_size=0.05, cols=64, rows=48)
             if kind == "cone" else ScanGeometry.parallel(angles, pixel_size=0.05, cols=64, rows=48))
        item = sphere_surface([0.2, -0.1, 0.1], 0.6, -0.3)
        r0, c0, rows, cols = np.array([0, 5, 10, 3, 8]), np.array([3, 10, 20, 0, 30]), 38, 34
    w = g.window(r0, c0, rows, cols)
    assert w.shape == (5, rows, cols) if rows else (5, cols)
    full = MeshProjector(g).forward(item)
    part = MeshProjector(w).forward(item)
    assert np.abs(part).max() > 0.1
    np.testing.assert_allclose(part, ScanGeometry.window_of(full, r0, c0, rows, cols), atol=1e-5)
    # the detector coordinates of a point move by the window's offset
    col_full, row_full, _ = g.detector_coordinates([[0.3, 0.2, 0.1]] if kind != "fan" else [[0.3, 0.2]])
    col_w, row_w, _ = w.detector_coordinates([[0.3, 0.2, 0.1]] if kind != "fan" else [[0.3, 0.2]])
    np.testing.assert_allclose(col_full[:, 0] + g.det_cols / 2, col_w[:, 0] + cols / 2 + c0, atol=1e-9)
    if rows:
        np.testing.assert_allclose(row_full[:, 0] + g.det_rows / 2, row_w[:, 0] + rows / 2 + r0, atol=1e-9)
    with pytest.raises(ValueError, match="leave the detector"):
        g.window(r0, c0 + 40, rows, cols)


@pytest.mark.parametrize("kind", ["cone", "parallel", "fan"])
def test_a_moved_geometry_projects_a_moving_sample_standing_still(kind):
    from bubsub.core import MeshProjector, circle_surface, sphere_surface

    angles = np.linspace(0, np.pi, 6, endpoint=False)
    nd = 2 if kind == "fan" else 3
    if kind == "fan":
        g = ScanGeometry.cone(angles, source_origin=40.0, origin_detector=10.0, pixel_size=0.05, cols=64)
    elif kind == "cone":
        g = ScanGeometry.cone(angles, source_origin=40.0, origin_detector=10.0, pixel_size=0.05, cols=64, rows=48)
    else:
        g = ScanGeometry.parallel(angles, pixel_size=0.05, cols=64, rows=48)
    centre = np.array([0.2, -0.1, 0.1][:nd])
    make = (lambda c: circle_surface(c, 0.5, -0.3)) if nd == 2 else (lambda c: sphere_surface(c, 0.5, -0.3))
    # the sample moves 0.02 mm per view, mostly along the rotation axis (across the rows in 2D)
    d = np.outer(np.arange(6) - 2.5, [0.004, 0.0, 0.02][:nd] if nd == 3 else [0.004, 0.02])
    moving = np.stack([MeshProjector(g[k:k + 1]).forward(make(centre + d[k]))[0] for k in range(6)])
    assert np.abs(moving).max() > 0.1
    still = MeshProjector(g.moved(d)).forward(make(centre))
    np.testing.assert_allclose(still, moving, atol=1e-5)
    # against the geometry that does not follow, the moving sample differs
    assert np.abs(MeshProjector(g).forward(make(centre)) - moving).max() > 0.05
    assert repr(g.moved(d)).endswith(".moved(<6 x %d displacements>)" % nd)
    with pytest.raises(ValueError, match="displacements must be"):
        g.moved(d[:5])
