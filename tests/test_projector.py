"""The mesh projector against independent truths: exact convex chords, analytic
spheres and ellipsoids, finite differences, ASTRA, and invariances.

Every test runs on every backend. The raster backend is exact in float64, so
where a truth is exact its values (``trace(...).values``, before the float32
output) are held to 1e-9 relative; the Embree backends cast float32 rays."""

import numpy as np
import pytest

from bubsub.core import Mesh, MeshProjector, Polygon, ScanGeometry, circle_surface, icosphere, sphere_surface
from bubsub.core.projection.backends import NAMES, available_backends, embree_native
from conftest import convex_chords, convex_mesh, sphere_chords

BACKENDS = list(NAMES)


@pytest.fixture(autouse=True, params=BACKENDS)
def backend(request, monkeypatch):
    """Every test of this module runs on every backend."""
    if request.param not in available_backends():
        pytest.fail(f"the {request.param} backend should be available in the test environment")
    monkeypatch.setenv("BUBSUB_BACKEND", request.param)
    return request.param


def values64(projector, items):
    """The projection before its float32 rounding, averaged over sub-rays."""
    k = projector.supersampling
    k2 = k * k if projector.geometry.ndim == 3 else k
    return projector.trace(items).values.reshape(projector.geometry.shape) / k2


def exact_tolerance(backend, scale):
    """Absolute tolerance for an exact truth of size ``scale``: 1e-9 relative for the float64 raster backend."""
    return 1e-9 * scale if backend == "raster" else 1e-4


def random_geometry(rng, kind, n_angles=4, rows=24, cols=32, source=300.0, pixel=0.12):
    ang = rng.uniform(0, 2 * np.pi, n_angles)
    if kind == "parallel3d":
        return ScanGeometry.parallel(ang, pixel_size=pixel, cols=cols, rows=rows)
    if kind == "cone":
        return ScanGeometry.cone(ang, source_origin=source, origin_detector=15.0, pixel_size=pixel, cols=cols, rows=rows)
    if kind == "parallel":
        return ScanGeometry.parallel(ang, pixel_size=pixel, cols=cols)
    return ScanGeometry.cone(ang, source_origin=source, origin_detector=15.0, pixel_size=pixel, cols=cols)


def random_vector_geometry(rng, rows=20, cols=24, n=3):
    """A non-circular cone_vec geometry: random source positions and tilted detectors."""
    rows_ = []
    for _ in range(n):
        src = rng.normal(size=3)
        src *= 80 / np.linalg.norm(src)
        axis = -src / np.linalg.norm(src)
        u = np.cross(axis, rng.normal(size=3))
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        rows_.append(np.concatenate([src, -0.2 * src, 0.15 * u, 0.13 * v]))
    return ScanGeometry.from_astra("cone_vec", np.array(rows_), det_rows=rows, det_cols=cols)


def first_rays(g, k=1):
    o, d = g.rays(k)
    return o, d


@pytest.mark.parametrize("kind, source", [("parallel3d", None), ("cone", 300.0), ("cone", 50_000.0)])
def test_convex_polyhedron_chords_are_exact(rng, kind, source, backend):
    pts = rng.normal(size=(40, 3)) * [1.0, 0.8, 0.6] + rng.uniform(-0.3, 0.3, 3)
    mesh = convex_mesh(pts, attenuation=0.7)
    g = random_geometry(rng, kind, source=source or 300.0)
    P = MeshProjector(g)
    p = P.forward([mesh])
    o, d = first_rays(g)
    truth = 0.7 * convex_chords(mesh, o[..., 0, :], d[..., 0, :])
    assert p.dtype == np.float32 and p.shape == g.shape
    assert truth.max() > 1.0  # the object is in view
    np.testing.assert_allclose(values64(P, [mesh]), truth, rtol=0, atol=exact_tolerance(backend, truth.max()))
    # float32 rays: a face at grazing incidence amplifies the 1e-7 ray offset
    np.testing.assert_allclose(p, truth, atol=1e-4)
    assert np.median(np.abs(p - truth)[truth > 0]) < 2e-6


def test_convex_chords_exact_for_non_circular_vector_geometry(rng, backend):
    mesh = convex_mesh(rng.normal(size=(30, 3)), attenuation=1.0)
    g = random_vector_geometry(rng)
    o, d = first_rays(g)
    P = MeshProjector(g)
    p, truth = P.forward(mesh), convex_chords(mesh, o[..., 0, :], d[..., 0, :])
    np.testing.assert_allclose(p, truth, atol=1e-4)  # float32 rays on grazing faces, as above
    np.testing.assert_allclose(values64(P, mesh), truth, rtol=0, atol=exact_tolerance(backend, truth.max()))
    assert np.median(np.abs(p - truth)[truth > 0]) < 2e-6


def box_classes(projector, meshes):
    """How many triangles the raster backend's candidate pass sorts into each way through a chunk,
    over all projections: boxes of one or two lattice points, 2 x 2 boxes, larger ones."""
    from bubsub.core.projection.backends import raster_kernels as K
    from bubsub.core.projection.backends.base import Scene
    from bubsub.core.projection.backends.raster import _Job

    job = _Job(Scene(meshes, 3, False), projector._frames, projector._sub, 1)
    S, D, U, V, N, Au, Bv = job.frames
    XY, iW = np.empty((len(job.vertices), 2)), np.empty(len(job.vertices))
    w, flags, idx, sidx, _, _ = K.chunk_buffers()
    counts = np.zeros(3, int)
    for p in range(projector.geometry.n_angles):
        K.project_all(job.vertices, p, job.cone, S, D, N, Au, Bv, job.rows, job.cols, 1, XY, iW)
        for s in range(0, len(job.faces), K.CHUNK):
            n_other, n_small = K.chunk_candidates(job.faces, s, min(K.CHUNK, len(job.faces) - s), XY, 0.0,
                                                  job.cols - 1.0, 0.0, job.rows - 1.0, w, flags, idx, sidx)
            j = idx[:n_other]
            box = w.reshape(-1, K.CHUNK)[K.BOX:K.BOX + 4, j]
            quad = (box[1] - box[0] == 1) & (box[3] - box[2] == 1)
            counts += [n_small, quad.sum(), n_other - quad.sum()]
    return counts


@pytest.mark.parametrize("kind", ["cone", "parallel3d"])
def test_triangles_of_every_size_are_exact(rng, kind, backend):
    """The raster backend takes a chunk's triangles three ways by the lattice box of their projection
    (one or two points; 2 x 2; larger): a convex mesh with triangles from a fraction of a pixel to
    many pixels is exact against its chords, and the candidate pass finds all three kinds on it."""
    directions = rng.normal(size=(1500, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    # points dense on one cap (triangles about a pixel), sparse elsewhere (triangles of many pixels)
    keep = (directions[:, 2] > 0.3) | (rng.uniform(size=len(directions)) < 0.03)
    mesh = convex_mesh(directions[keep] * [1.0, 0.8, 0.7], attenuation=0.6)
    g = random_geometry(rng, kind, rows=40, cols=48, pixel=0.06)
    P = MeshProjector(g)
    o, d = first_rays(g)
    truth = 0.6 * convex_chords(mesh, o[..., 0, :], d[..., 0, :])
    assert truth.max() > 1.0
    np.testing.assert_allclose(values64(P, [mesh]), truth, rtol=0, atol=exact_tolerance(backend, truth.max()))
    if backend == "raster":
        assert (box_classes(P, [mesh]) > 100).all()


@pytest.mark.parametrize("kind", ["parallel3d", "cone"])
def test_fine_sphere_and_ellipsoid_match_analytic_chords(rng, kind):
    v, f = icosphere(4)  # 5120 triangles
    g = random_geometry(rng, kind, rows=32, cols=40, pixel=0.08)
    o, d = first_rays(g)
    o, d = o[..., 0, :], d[..., 0, :]
    centre = np.array([0.2, -0.1, 0.15])
    radii = np.array([1.2, 0.9, 0.7])
    p = MeshProjector(g).forward(Mesh(v * radii + centre, f, 0.5))
    # an ellipsoid is a scaled sphere: scale rays into the unit sphere's frame
    os_, ds = (o - centre) / radii, d / radii
    scale = np.linalg.norm(ds, axis=-1)
    truth = 0.5 * sphere_chords(np.zeros(3), 1.0, os_, ds / scale[..., None]) / scale
    inner = truth > 0.5 * truth.max()
    # faceting of the level-4 icosphere shortens chords by < 0.5% away from the silhouette
    np.testing.assert_allclose(p[inner], truth[inner], rtol=5e-3)
    assert abs(p.sum() - truth.sum()) / truth.sum() < 5e-3


def test_parallel_projection_conserves_mass(rng):
    # Parallel beam: sum over the detector x pixel area = attenuation x volume, for every angle
    s = sphere_surface([0.1, 0.3, -0.2], 1.0, 0.4)
    mesh = s.fine()
    g = ScanGeometry.parallel(rng.uniform(0, np.pi, 3), pixel_size=0.05, cols=64, rows=64)
    p = MeshProjector(g, supersampling=2).forward([mesh])
    np.testing.assert_allclose(p.sum(axis=(1, 2)) * 0.05**2, 0.4 * mesh.volume, rtol=2e-3)


@pytest.mark.parametrize("kind", ["cone", "parallel3d", "fanflat"])
def test_supersampling_averages_exact_sub_ray_chords(rng, kind, backend):
    mesh = convex_mesh(rng.normal(size=(25, 3)), attenuation=1.0)
    g = random_geometry(rng, kind, rows=10, cols=12, pixel=0.4)
    o, d = g.rays(3)
    if g.ndim == 2:  # a 2D polygon is a prism's cross-section: chords of the prism in the plane z = 0
        poly = Polygon(np.array([[np.cos(a), np.sin(a)] for a in np.linspace(0, 2 * np.pi, 7)[:-1]]) * 1.3 + [0.2, -0.1], 1.0)
        mesh3 = convex_mesh(np.concatenate([np.c_[poly.vertices, np.full(6, z)] for z in (-5.0, 5.0)]))
        truth, item = convex_chords(mesh3, o, d).mean(axis=-1), poly
    else:
        truth, item = convex_chords(mesh, o, d).mean(axis=-1), mesh
    P = MeshProjector(g, supersampling=3)
    np.testing.assert_allclose(P.forward(item), truth, atol=2e-5)
    np.testing.assert_allclose(values64(P, item), truth, rtol=0, atol=exact_tolerance(backend, truth.max()))


def test_nested_container_and_bubbles_add_up(rng):
    g = random_geometry(rng, "cone", rows=20, cols=28, pixel=0.2)
    box = convex_mesh(np.array([[x, y, z] for x in (-2, 2) for y in (-2, 2) for z in (-1.5, 1.5)], float), 0.1)
    b1 = sphere_surface([0.8, 0.5, 0.0], 0.6, -0.1).fine()
    b2 = sphere_surface([-0.7, -0.6, 0.3], 0.5, -0.1).fine()
    P = MeshProjector(g)
    together = P.forward([box, b1, b2])
    apart = P.forward([box]).astype(float) + P.forward([b1]) + P.forward([b2])
    np.testing.assert_allclose(together, apart, atol=1e-5)
    assert together.min() >= -1e-6  # gas never makes negative line integrals inside liquid


def test_rays_through_edges_and_vertices_count_once():
    # Axis-aligned cube, parallel rays along x on a grid that hits its edges and corners exactly
    cube = convex_mesh(np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float), 1.0)
    vec = np.array([[1.0, 0, 0, 5, 0, 0, 0, 0.25, 0, 0, 0, 0.25]])
    g = ScanGeometry.from_astra("parallel3d_vec", vec, det_rows=16, det_cols=16)
    p = MeshProjector(g).forward(cube)
    # pixel centres at -1.875 ... 1.875 in steps of 0.25: none on the faces, so every value is 0 or 2
    assert set(np.round(np.unique(p), 5)) <= {0.0, 2.0}
    vec2 = vec.copy()
    vec2[0, 3:6] = [5, 0.125, 0.125]  # now rays run exactly along the cube's edges and faces
    p2 = MeshProjector(ScanGeometry.from_astra("parallel3d_vec", vec2, det_rows=16, det_cols=16)).forward(cube)
    assert p2.max() <= 2.0 + 1e-5 and p2.min() >= -1e-5
    # and through the icosahedron's vertices along its axes
    v, f = icosphere(0)
    ico = Mesh(v, f)
    dirs = v / np.linalg.norm(v, axis=1, keepdims=True)
    for d in dirs[:6]:
        u = np.cross(d, [0.3, 0.5, 0.7])
        u /= np.linalg.norm(u)
        w = np.cross(d, u)
        gv = ScanGeometry.from_astra("parallel3d_vec", np.concatenate([d, -3 * d, 0.01 * u, 0.01 * w])[None], det_rows=2, det_cols=2)
        val = MeshProjector(gv).forward(ico)
        truth = convex_chords(ico, *(a[..., 0, :] for a in gv.rays()))
        np.testing.assert_allclose(val, truth, atol=1e-4)


def lattice_scan(rows, cols, pitch=0.25):
    """One parallel projection along +x whose pixel centres sit at multiples of ``pitch`` in y and z."""
    vec = np.array([[1.0, 0, 0, 5, pitch / 2, pitch / 2, 0, pitch, 0, 0, 0, pitch]])
    g = ScanGeometry.from_astra("parallel3d_vec", vec, det_rows=rows, det_cols=cols)
    yz = g.pixel_centres()[0][..., 1:]
    return g, yz


def test_pixel_centres_on_projected_edges_of_a_cube_count_once(backend):
    cube = convex_mesh(np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float), 1.0)
    g, yz = lattice_scan(16, 16)
    # the face diagonals (|y| = |z|) are edges between two front (or two back) triangles
    on_diagonal = np.abs(np.abs(yz[..., 0]) - np.abs(yz[..., 1])) == 0
    inside = np.all(np.abs(yz) < 1, axis=-1)
    outside = np.any(np.abs(yz) > 1, axis=-1)
    assert (on_diagonal & inside).sum() >= 10
    v = values64(MeshProjector(g), cube)[0]
    tol = exact_tolerance(backend, 2.0)
    np.testing.assert_allclose(v[inside], 2.0, rtol=0, atol=tol)
    np.testing.assert_array_equal(v[outside], 0.0)


def test_pixel_centres_on_projected_vertices_count_once(rng, backend):
    """A convex polyhedron whose vertices all project onto pixel centres (and its edges through many more)."""
    from scipy.spatial import ConvexHull

    grid = np.array([[y, z] for y in range(-6, 7) for z in range(-6, 7) if y * y + z * z <= 36], float) * 0.25
    pick = grid[rng.choice(len(grid), 40, replace=False)]
    pts = np.c_[rng.normal(scale=1.0, size=len(pick)), pick]
    mesh = convex_mesh(pts, 0.6)
    g, yz = lattice_scan(24, 24)
    o, d = g.rays()
    truth = 0.6 * convex_chords(mesh, o[..., 0, :], d[..., 0, :])[0]
    hull = ConvexHull(mesh.vertices[:, 1:])
    # on the silhouette a ray only touches the surface: what it gets there is a matter of convention
    dist = yz.reshape(-1, 2) @ hull.equations[:, :2].T + hull.equations[:, 2]
    silhouette = np.any(np.abs(dist) < 1e-12, axis=1).reshape(yz.shape[:2])
    on_vertex = np.zeros(yz.shape[:2], bool)
    for y, z in mesh.vertices[:, 1:]:
        on_vertex |= (yz[..., 0] == y) & (yz[..., 1] == z)
    assert (on_vertex & ~silhouette).sum() >= 5  # vertices inside the projection, hit exactly
    v = values64(MeshProjector(g), mesh)[0]
    np.testing.assert_allclose(v[~silhouette], truth[~silhouette], rtol=0, atol=exact_tolerance(backend, truth.max()))


def test_translation_of_scene_and_geometry_together_changes_nothing(rng):
    g = random_geometry(rng, "cone", rows=16, cols=20, pixel=0.2)
    s = sphere_surface([0.2, 0.1, -0.1], 0.9, 0.5)
    shift = np.array([1000.0, -700.0, 250.0])
    vec = g.vectors.copy()
    vec[:, 0:3] += shift
    vec[:, 3:6] += shift
    g2 = ScanGeometry.from_astra("cone_vec", vec, det_rows=16, det_cols=20)
    a = MeshProjector(g).forward(s)
    b = MeshProjector(g2).forward(s.with_vertices(s.vertices + shift))
    assert a.max() > 0.5
    np.testing.assert_allclose(a, b, atol=2e-5)


def smooth_field(rng, x, amplitude=0.05):
    """A random smooth displacement field evaluated at points x (n, d)."""
    d = x.shape[1]
    k = rng.normal(size=(3, d)) * 1.5
    a = rng.normal(size=(3, d))
    ph = rng.uniform(0, 2 * np.pi, 3)
    return amplitude * sum(a[i] * np.sin(x @ k[i] + ph[i])[:, None] for i in range(3))


@pytest.mark.parametrize("kind", ["parallel3d", "cone", "parallel", "fanflat"])
def test_vjp_matches_central_finite_differences(rng, kind):
    g = random_geometry(rng, kind, n_angles=5, rows=24, cols=48, pixel=0.07)
    if g.ndim == 3:
        items = [sphere_surface([0.3, 0.2, 0.0], 0.8, -0.1), sphere_surface([-0.9, -0.6, 0.2], 0.5, 0.2)]
    else:
        items = [circle_surface([0.3, 0.2], 0.8, -0.1), circle_surface([-0.9, -0.6], 0.5, 0.2)]
    P = MeshProjector(g, supersampling=2)
    r = rng.normal(size=g.shape)
    grads = P.vjp(items, r)
    dirs = [smooth_field(rng, s.vertices) for s in items]
    analytic = sum(np.vdot(gr, dv) for gr, dv in zip(grads, dirs))
    # the chord is only piecewise smooth (silhouette rays) and the projection
    # float32: a step between those two noise floors
    h = 3e-4

    def value(sign):
        moved = [s.with_vertices(s.vertices + sign * h * dv) for s, dv in zip(items, dirs)]
        return np.vdot(P.forward(moved).astype(float), r)

    numeric = (value(1) - value(-1)) / (2 * h)
    # the scale of the sum, so a cancelling sum is not judged by its tiny remainder
    scale = sum(np.abs(gr * dv).sum() for gr, dv in zip(grads, dirs))
    assert scale > 1e-2
    # silhouette kinks leave about 1 % of the scale; a wrong factor or sign leaves far more
    assert abs(numeric - analytic) < 2e-2 * scale


def test_objective_shares_one_traversal_and_agrees_with_forward_and_vjp(rng):
    g = random_geometry(rng, "cone", rows=16, cols=24, pixel=0.15)
    s = sphere_surface([0.1, 0.0, 0.0], 1.0, -0.1)
    P = MeshProjector(g)
    data = P.forward(s.with_vertices(s.vertices * 1.1)).astype(np.float64) + rng.normal(scale=1e-3, size=g.shape)
    f, grads = P.objective([s], data)
    res = P.forward([s]).astype(float) - data
    assert f == pytest.approx(0.5 * np.sum(res**2), rel=1e-9)
    np.testing.assert_allclose(grads[0], P.vjp([s], res)[0], rtol=1e-6, atol=1e-9)
    # the gradient points uphill: a small step against it lowers f
    f2, _ = P.objective([s.with_vertices(s.vertices - 1e-3 * grads[0] / np.abs(grads[0]).max())], data)
    assert f2 < f


@pytest.mark.parametrize("supersampling, dtype", [(1, np.float32), (2, np.float64), (3, np.int32)])
def test_objective_is_the_misfit_of_the_float32_forward_projection(rng, supersampling, dtype):
    # the objective's fused residual rounds the projection to float32 as forward() does, for every
    # sub-ray count and data type
    g = random_geometry(rng, "cone", rows=12, cols=20, pixel=0.2)
    s = sphere_surface([0.0, 0.1, 0.0], 0.9, -0.7)
    P = MeshProjector(g, supersampling=supersampling)
    data = (P.forward(s.with_vertices(s.vertices * 1.05)) * 3).astype(dtype)
    f, grads = P.objective([s], data)
    res = P.forward([s]).astype(np.float64) - data.astype(np.float64)
    assert f > 0
    assert f == pytest.approx(0.5 * np.sum(res**2), rel=1e-12)
    np.testing.assert_allclose(grads[0], P.vjp([s], res)[0], rtol=1e-9, atol=1e-12)


def test_threads_do_not_change_results(rng):
    g = random_geometry(rng, "cone", rows=64, cols=96, pixel=0.05, n_angles=12)
    items = [sphere_surface(rng.uniform(-1, 1, 3), 0.5, -0.1) for _ in range(4)]
    r = rng.normal(size=g.shape)
    a = MeshProjector(g, threads=1)
    b = MeshProjector(g, threads=2)
    np.testing.assert_array_equal(a.forward(items), b.forward(items))
    for x, y in zip(a.vjp(items, r), b.vjp(items, r)):
        np.testing.assert_allclose(x, y, rtol=1e-10, atol=1e-12)


def test_objective_on_a_large_detector_is_summed_in_chunks_per_thread(rng):
    # over 2**18 pixels per thread the residual runs in one chunk per thread: f must stay the float64 misfit
    g = random_geometry(rng, "cone", rows=256, cols=512, pixel=0.02, n_angles=6)
    s = sphere_surface([0.0, 0.1, 0.0], 1.5, -0.7)
    data = MeshProjector(g, threads=1).forward([s.with_vertices(s.vertices * 1.05)])
    data = data + rng.normal(0, 0.01, g.shape).astype(np.float32)
    res = MeshProjector(g, threads=1).forward([s]).astype(np.float64) - data
    truth = 0.5 * np.sum(res**2)
    for threads in (1, 2, 3):
        f, _ = MeshProjector(g, threads=threads).objective([s], data)
        assert f == pytest.approx(truth, rel=1e-12)


def test_2d_matches_astra_projection_of_a_voxelised_disk():
    astra = pytest.importorskip("astra")
    n, px = 1000, 0.004  # 4 mm field, fine grid
    centre, radius, mu = np.array([0.35, -0.5]), 1.1, 0.25
    ang = np.linspace(0, np.pi, 6, endpoint=False)
    g = ScanGeometry.parallel(ang, pixel_size=0.02, cols=240)
    # image row 0 at y max, x increasing with column
    x = (np.arange(n) + 0.5) * px - n * px / 2
    X, Y = np.meshgrid(x, -x)
    img = (mu * ((X - centre[0]) ** 2 + (Y - centre[1]) ** 2 <= radius**2)).astype(np.float32)
    vol = astra.create_vol_geom(n, n, -n * px / 2, n * px / 2, -n * px / 2, n * px / 2)
    pid = astra.create_projector("strip", g.to_astra(), vol)  # integrates over the pixel width
    sid, sino = astra.create_sino(img, pid)
    astra.data2d.delete(sid)
    a = np.linspace(0, 2 * np.pi, 4000, endpoint=False)
    disk = Polygon(centre + radius * np.c_[np.cos(a), np.sin(a)], mu)
    ours = MeshProjector(g, supersampling=8).forward([disk])
    assert ours.max() == pytest.approx(2 * radius * mu, rel=1e-3)
    # what is left is the voxelisation of the disk's edge
    assert np.abs(ours - sino).max() < 0.01 * 2 * radius * mu
    assert np.abs(ours - sino).mean() < 4e-4 * 2 * radius * mu
    # and a flipped image (the wrong convention) would be far off
    sid, flipped = astra.create_sino(img[::-1], pid)
    astra.data2d.delete(sid)
    astra.projector.delete(pid)
    assert np.abs(ours - flipped).max() > 0.2


@pytest.mark.parametrize("kind", ["fanflat", "parallel"])
def test_2d_polygon_chords_are_exact(rng, kind, backend):
    g = random_geometry(rng, kind, cols=64, pixel=0.05)
    sq = Polygon(np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * 0.8, 1.0)
    box = convex_mesh(np.array([[x, y, z] for x in (-0.8, 0.8) for y in (-0.8, 0.8) for z in (-5, 5)], float))
    o, d = g.rays()
    truth = convex_chords(box, o[..., 0, :], d[..., 0, :])
    P = MeshProjector(g)
    np.testing.assert_allclose(P.forward(sq), truth, atol=2e-5)
    np.testing.assert_allclose(values64(P, sq), truth, rtol=0, atol=exact_tolerance(backend, truth.max()))


def test_bad_input_is_refused_clearly(rng):
    g = random_geometry(rng, "cone", rows=4, cols=5)
    P = MeshProjector(g)
    s = sphere_surface([0, 0, 0], 0.5, -0.1)
    with pytest.raises(ValueError, match=r"shape \(4, 4, 5\)"):
        P.objective([s], np.zeros((4, 5, 4)))
    with pytest.raises(ValueError, match="NaN"):
        P.objective([s], np.full(g.shape, np.nan))
    with pytest.raises(ValueError, match="dtype"):
        P.vjp([s], np.zeros(g.shape, complex))
    with pytest.raises(TypeError, match="2D geometry projects Polygon"):
        MeshProjector(random_geometry(rng, "parallel")).forward([s])
    with pytest.raises(ValueError, match="nothing to project"):
        P.forward([])
    with pytest.raises(ValueError, match="supersampling"):
        MeshProjector(g, supersampling=0)
    with pytest.raises(TypeError, match="ScanGeometry"):
        MeshProjector("cone")
    # a bubble around the cone source has no central projection
    near = ScanGeometry.cone([0.0], source_origin=2.0, origin_detector=15.0, pixel_size=0.1, cols=8, rows=8)
    with pytest.raises(ValueError, match="item 1 has a vertex .* behind .* cone source of projection 0"):
        MeshProjector(near).forward([sphere_surface([0, 0, 0], 0.5, -0.1), sphere_surface([0, -2, 0], 0.5, -0.1)])
    fan = ScanGeometry.cone([0.0, 1.0], source_origin=2.0, origin_detector=15.0, pixel_size=0.1, cols=8)
    with pytest.raises(ValueError, match="behind .* cone source of projection 1"):
        MeshProjector(fan).forward(circle_surface([1.6, -1.0], 0.5, -0.1))


def test_backend_is_the_one_asked_for(backend, rng):
    g = random_geometry(rng, "cone", rows=4, cols=5)
    assert MeshProjector(g).backend == backend
    assert f"backend={backend!r}" in repr(MeshProjector(g))
    with pytest.raises(ValueError, match="backend must be"):
        MeshProjector(g, backend="optix")


def test_backends_agree_on_a_foam(rng, backend):
    """Cross-backend consistency on a many-bubble scene: projections and gradients (raster against native)."""
    g = random_geometry(rng, "cone", rows=48, cols=64, pixel=0.08, n_angles=6)
    spheres = []
    while len(spheres) < 12:
        c, r = rng.uniform(-1.6, 1.6, 3), rng.uniform(0.2, 0.45)
        if all(np.linalg.norm(c - c2) > r + r2 + 0.05 for c2, r2 in spheres):
            spheres.append((c, r))
    items = []
    for c, r in spheres:
        s = sphere_surface(c, r, -0.1)
        items.append(s.with_vertices(s.vertices + 0.03 * r * rng.normal(size=s.vertices.shape)))
    other = "native" if backend == "raster" else "raster"
    a, b = MeshProjector(g, backend=backend), MeshProjector(g, backend=other)
    pa, pb = a.forward(items), b.forward(items)
    assert np.abs(pa).max() > 0.05
    np.testing.assert_allclose(pa, pb, atol=2e-5)
    data = pb + np.float32(0.01) * rng.normal(size=g.shape).astype(np.float32)
    (fa, ga), (fb, gb) = a.objective(items, data), b.objective(items, data)
    assert fa == pytest.approx(fb, rel=1e-4)
    for x, y in zip(ga, gb):
        np.testing.assert_allclose(x, y, rtol=1e-3, atol=1e-4 * np.abs(y).max())


@pytest.mark.parametrize("kind", ["cone", "parallel3d"])
def test_item_by_item_forward_pass_is_the_projection_by_projection_one(rng, monkeypatch, kind, backend):
    """Large scenes are rasterised item by item (each through all projections of a thread's group):
    the projection, crossing count and f are the same to the bit as projection by projection, the
    gradient to rounding (its face sums are split among threads by items, so a face's crossings
    are added in another grouping), and exact against the convex chords (the other backends
    ignore the switch)."""
    from bubsub.core.projection.backends import raster

    g = random_geometry(rng, kind, rows=24, cols=32, pixel=0.12, n_angles=5)
    centres = [[-1.0, -0.4, 0.1], [0.9, 0.3, -0.2], [0.0, 0.8, 0.3]]
    convex = [convex_mesh(c + 0.35 * rng.normal(size=(30, 3)), attenuation=0.4 + 0.2 * i) for i, c in enumerate(centres)]
    items = convex + [sphere_surface([0.1, -0.6, -0.1], 0.3, -0.2, levels=2)]
    data = rng.normal(size=g.shape).astype(np.float32)

    def run():
        P = MeshProjector(g, threads=2)
        traversal = P.trace(items)
        return traversal.values.copy(), traversal.count, P.objective(items, data)

    projection_major = run()
    monkeypatch.setattr(raster, "ITEM_MAJOR_FACES", 0)
    item_major = run()
    np.testing.assert_array_equal(item_major[0], projection_major[0])
    assert item_major[1] == projection_major[1] > 0
    assert item_major[2][0] == projection_major[2][0]
    for a, b in zip(item_major[2][1], projection_major[2][1]):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max())
    only_convex = MeshProjector(g)
    o, d = first_rays(g)
    truth = sum(m.attenuation * convex_chords(m, o[..., 0, :], d[..., 0, :]) for m in convex)
    np.testing.assert_allclose(values64(only_convex, convex), truth, rtol=0, atol=exact_tolerance(backend, truth.max()))


@pytest.mark.parametrize("kind", ["cone", "parallel3d"])
def test_gradient_is_the_same_from_stored_and_from_rasterised_crossings(rng, monkeypatch, kind):
    """The raster forward pass keeps crossings for the gradient within BUBSUB_RASTER_STORE_MB; a full,
    an overflowing (groups fall back: at once, or after keeping about half their crossings) and a
    disabled store give the same objective and gradient (the other backends ignore the setting)."""
    g = random_geometry(rng, kind, rows=24, cols=32, pixel=0.12, n_angles=5)
    items = [sphere_surface(c, 0.5, -0.2) for c in ([-0.7, 0.1, 0.0], [0.6, -0.2, 0.1])]
    items = [s.with_vertices(s.vertices + 0.03 * rng.normal(size=s.vertices.shape)) for s in items]
    data = MeshProjector(g).forward(items) * np.float32(0.9)
    # about half of each group's crossings: a store that fills after keeping some
    half = f"{MeshProjector(g).trace(items).count * 32 / 2 / 2**20:.6f}"
    results = {}
    for mb in ("", "0.001", half, "0"):  # default (all kept), too small for one group, half, none
        monkeypatch.setenv("BUBSUB_RASTER_STORE_MB", mb)
        results[mb] = MeshProjector(g, threads=2).objective(items, data)
    f0, g0 = results[""]
    assert np.abs(g0[0]).max() > 0
    P = MeshProjector(g, threads=2)
    if P.backend == "raster":  # the default budget keeps every group's crossings; a tiny one overflows
        monkeypatch.setenv("BUBSUB_RASTER_STORE_MB", "")
        assert all(s[3] > 0 for s in P._trace(P._scene(items), gradient=True)._job.stores.values())
        for mb in ("0.001", half):
            monkeypatch.setenv("BUBSUB_RASTER_STORE_MB", mb)
            assert any(s[3] < 0 for s in P._trace(P._scene(items), gradient=True)._job.stores.values())
    for mb in ("0.001", half, "0"):
        f, grads = results[mb]
        assert f == pytest.approx(f0, rel=1e-12)
        for x, y in zip(grads, g0):
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12 * np.abs(y).max())
    monkeypatch.setenv("BUBSUB_RASTER_STORE_MB", "lots")
    if MeshProjector(g).backend == "raster":
        with pytest.raises(ValueError, match="BUBSUB_RASTER_STORE_MB"):
            MeshProjector(g).objective(items, data)


@pytest.mark.parametrize("kind, sub", [("cone", 1), ("parallel3d", 1), ("parallel3d", 2)])
def test_objective_view_by_view_is_the_residual_of_forward_and_its_vjp(rng, monkeypatch, kind, sub):
    """The raster objective takes each chunk of views' residual and face sums while its crossings are
    stored (RasterBackend.objective); whatever the store holds (all, a view's worth or so, less than a
    view, nothing), it is 0.5 |forward - data|^2 and the vjp of that residual, from separate passes."""
    g = random_geometry(rng, kind, rows=24, cols=32, pixel=0.12, n_angles=7)
    items = [sphere_surface(c, 0.5, -0.2) for c in ([-0.7, 0.1, 0.0], [0.6, -0.2, 0.1], [0.0, 0.3, -0.2])]
    items = [s.with_vertices(s.vertices + 0.03 * rng.normal(size=s.vertices.shape)) for s in items]
    P = MeshProjector(g, threads=2, supersampling=sub)
    data = P.forward(items) * np.float32(0.9) + np.float32(0.01)
    residual = P.forward(items).astype(np.float64) - data
    f_ref, g_ref = 0.5 * float(np.sum(residual ** 2)), P.vjp(items, residual)
    assert np.abs(g_ref[0]).max() > 0
    view = P.trace(items).count * 32 / g.n_angles / 2**20
    for mb in ("", f"{1.5 * view:.6f}", f"{0.3 * view:.6f}", "0"):
        monkeypatch.setenv("BUBSUB_RASTER_STORE_MB", mb)
        f, grads = P.objective(items, data)
        assert f == pytest.approx(f_ref, rel=1e-12)
        for x, y in zip(grads, g_ref):
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12 * np.abs(y).max())


def test_a_reused_crossing_store_gives_the_same_objective(rng):
    """The raster backend hands a finished gradient's crossing store back and the next call reuses it;
    stale entries from a larger scene must not leak into a smaller one's gradient."""
    from bubsub.core.projection.backends import raster

    g = random_geometry(rng, "cone", rows=24, cols=32, pixel=0.12, n_angles=5)
    P = MeshProjector(g, threads=2, backend="raster")
    small = [sphere_surface([0.1, 0.0, 0.0], 0.6, -0.2)]
    big = small + [sphere_surface([-0.8, 0.2, 0.0], 0.4, -0.2), sphere_surface([0.9, -0.1, 0.1], 0.3, -0.2)]
    data = P.forward(big) * np.float32(0.9)
    raster._POOL.clear()
    f1, g1 = P.objective(small, data)
    assert len(raster._POOL) == 1
    store = raster._POOL[0]
    P.objective(big, data)  # fills more of the same store
    assert raster._POOL[0] is store
    f2, g2 = P.objective(small, data)
    assert raster._POOL[0] is store
    assert f2 == f1
    np.testing.assert_array_equal(g2[0], g1[0])


def test_a_ray_through_hundreds_of_meshes_keeps_every_crossing():
    """260 crossings on one ray: more than the native backend's first hit buffer holds."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float) * 0.1 - 0.05
    cubes = [convex_mesh(corners + [0.2 * k, 0.0, 0.0], attenuation=0.5) for k in range(130)]
    vec = np.array([[1.0, 0, 0, 0, 0, 0, 0, 0.025, 0, 0, 0, 0.025]])  # rays along x, 0.025 mm pixels
    g = ScanGeometry.from_astra("parallel3d_vec", vec, det_rows=8, det_cols=8)
    p = MeshProjector(g).forward(cubes)
    inside = np.zeros((8, 8), bool)
    inside[2:6, 2:6] = True  # pixel centres within |y|, |z| < 0.05
    np.testing.assert_allclose(p[0][inside], 130 * 0.1 * 0.5, rtol=1e-5)
    np.testing.assert_array_equal(p[0][~inside], 0)


def test_compiled_code_falls_back_to_memory_when_no_cache_folder_is_writable(monkeypatch):
    numba = pytest.importorskip("numba")
    from numba.core import caching

    monkeypatch.setattr(caching.CacheImpl, "_locator_classes", [])  # a read-only install: nowhere to cache
    with pytest.raises(RuntimeError, match="cannot cache"):
        numba.njit(cache=True)(lambda x: x + 1)
    from bubsub.core.projection.backends.jit import cached

    twice = cached(numba.njit, nogil=True)(lambda x: 2 * x)
    assert twice(21) == 42


@pytest.mark.parametrize("parts", [1, 2, 3, 5, 12])
def test_scene_item_spans_cover_every_item_once_in_order(rng, parts):
    from bubsub.core.projection.backends.base import Scene

    sizes = [4, 40, 6, 300, 8, 12, 60]
    items = [convex_mesh(rng.normal(size=(n, 3)) + 5.0 * i) for i, n in enumerate(sizes)]
    scene = Scene(items, 3, False, threads=parts)
    spans = scene.item_spans(parts)
    assert 1 <= len(spans) <= parts
    assert spans[0][0] == 0 and spans[-1][1] == len(items)
    assert all(a < b for a, b in spans) and all(b == c for (_, b), (c, _) in zip(spans, spans[1:]))


def test_scene_steps_on_threads_are_the_serial_ones(rng, monkeypatch):
    """The scene's planes and the gradient's vertex scatter split by items over threads give the
    serial result to the bit (an item's faces use only its own vertices, in the same order)."""
    from bubsub.core.projection.backends import base

    items = [sphere_surface([0.6 * i - 0.9, 0.1 * i, 0.0], 0.25, 0.3 + 0.1 * i, levels=1) for i in range(4)]
    serial = base.Scene(items, 3, False, threads=1)
    monkeypatch.setattr(base, "THREADED_FACES", 0)
    threaded = base.Scene(items, 3, False, threads=3)
    assert len(threaded.face_spans()) == 3 and len(serial.face_spans()) == 1
    np.testing.assert_array_equal(threaded.normals, serial.normals)
    np.testing.assert_array_equal(threaded.offsets, serial.offsets)
    sums = rng.normal(size=serial.faces.shape)
    np.testing.assert_array_equal(base.vertex_gradient(threaded, sums), base.vertex_gradient(serial, sums))
