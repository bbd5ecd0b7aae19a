"""Dynamic (4D) scans: scan files cut into subscans, warm starts, the reconstruct4d chain."""

import csv
import json
import pickle
import re
import shutil
import warnings

import h5py
import numpy as np
import pytest

from bubsub.clients.cli import main
# imported before any test patches bubsub.clients.optimise.fit.fit: its module-level `fit` must stay the real one
from bubsub.clients.pipeline import reconstruct as _static_pipeline  # noqa: F401
from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, DynamicSettings, reconstruct_subscan
from bubsub.core import Mesh, ScanGeometry, circle_surface, sphere_surface
from bubsub.core.foam.expanding import expanding2d
from bubsub.core.io.meshio import read_polygons_json
from bubsub.core.io.scanfile import Scan, read_scan, write_scan
from bubsub.core.io.subscans import parse_subscan_range, subscan, subscan_layout, subscan_times
from bubsub.core.projection.remesh import resample_polygon, warm_start


def dynamic_scan(n_sub=3, k=4, cols=8, **kw):
    angles = np.tile(np.linspace(0, np.pi, k, endpoint=False), n_sub)
    g = ScanGeometry.parallel(angles, pixel_size=0.1, cols=cols)
    data = np.arange(np.prod(g.shape), dtype=np.float32).reshape(g.shape)
    return Scan(data=data, geometry=g, bubble_contrast=-0.1, time=np.arange(g.n_angles) * 0.5, **kw)


# -- scan files and subscans ------------------------------------------------------------------
def test_dynamic_scan_round_trip_and_old_files(tmp_path):
    scan = dynamic_scan(projections_per_subscan=4)
    back = read_scan(write_scan(tmp_path / "d.h5", scan))
    assert back.projections_per_subscan == 4
    assert np.array_equal(back.time, scan.time)
    assert "projections_per_subscan" not in back.attrs
    static = read_scan(write_scan(tmp_path / "s.h5", dynamic_scan()))
    assert static.time is not None and static.projections_per_subscan is None
    with h5py.File(tmp_path / "s.h5", "a") as f:  # a file from before dynamic scans
        del f["exchange/time"]
    assert read_scan(tmp_path / "s.h5").time is None


def test_background_of_one_subscan_is_repeated(tmp_path):
    scan = dynamic_scan(projections_per_subscan=4)
    path = write_scan(tmp_path / "d.h5", scan)
    one = np.random.default_rng(0).uniform(size=(4, 8)).astype(np.float32)
    with h5py.File(path, "a") as f:
        f.create_dataset("exchange/background", data=one)
    back = read_scan(path)
    assert back.background.shape == scan.data.shape
    for k in range(3):
        assert np.array_equal(back.background[4 * k:4 * k + 4], one)


def test_geometry_rows_that_do_not_match_are_named(tmp_path):
    scan = dynamic_scan(projections_per_subscan=4)
    path = write_scan(tmp_path / "d.h5", scan)
    with h5py.File(path, "a") as f:  # geometry of one subscan only
        v = f["geometry/vectors"][:4]
        attrs = dict(f["geometry/vectors"].attrs)
        del f["geometry/vectors"]
        ds = f.create_dataset("geometry/vectors", data=v)
        ds.attrs.update(attrs)
        del f["exchange/theta"]
    with pytest.raises(ValueError, match="one geometry row per projection"):
        read_scan(path)
    with pytest.raises(ValueError, match="one geometry row per projection"):  # the same scan made in memory
        Scan(data=scan.data, geometry=scan.geometry[:4], bubble_contrast=-0.1, projections_per_subscan=4)


def test_subscan_slices_are_the_right_projections():
    scan = dynamic_scan(projections_per_subscan=4)
    layout = subscan_layout(scan)
    assert (layout.n_subscans, layout.per_subscan, layout.leftover) == (3, 4, 0)
    s1 = subscan(scan, layout, 1)
    assert np.array_equal(s1.data, scan.data[4:8]) and s1.geometry == scan.geometry[4:8]
    assert s1.attrs["subscan"] == 1 and s1.projections_per_subscan is None
    times, unit = subscan_times(scan, layout)
    assert unit == "s" and np.allclose(times, [0.75, 2.75, 4.75])


def test_projections_per_subscan_that_does_not_divide():
    scan = dynamic_scan(n_sub=3, k=4)
    with pytest.warns(UserWarning, match="does not divide the scan's 12 projections: 2 complete subscans"):
        layout = subscan_layout(scan, 5)
    assert layout.n_subscans == 2 and layout.leftover == 2
    with pytest.raises(ValueError, match="does not divide"):
        subscan_layout(scan, 5, incomplete="error")


@pytest.mark.parametrize("given, message", [
    (dict(), "no root attribute 'projections_per_subscan'"),
    (dict(projections_per_subscan=20), "exceeds the scan's 12 projections"),
    (dict(projections_per_subscan=0), "positive integer"),
    (dict(projections_per_subscan=4, subscans="2:5"), "out of bounds: the scan has subscans 0..2"),
    (dict(projections_per_subscan=4, subscans="2:1"), "selects no subscan"),
    (dict(projections_per_subscan=4, subscans="a:b"), "integers"),
])
def test_bad_subscan_requests(given, message):
    with pytest.raises(ValueError, match=message):
        subscan_layout(dynamic_scan(), given.get("projections_per_subscan"), given.get("subscans"))


def test_projections_per_subscan_contradicting_the_file():
    with pytest.raises(ValueError, match="contradicts the scan file's attribute"):
        subscan_layout(dynamic_scan(projections_per_subscan=4), 6)


def test_subscan_ranges():
    assert parse_subscan_range("1:3", 5) == range(1, 3)
    assert parse_subscan_range(":", 5) == range(0, 5)
    assert parse_subscan_range("-2:", 5) == range(3, 5)
    assert parse_subscan_range("4", 5) == range(4, 5)


# -- warm starts ------------------------------------------------------------------------------
def test_resample_polygon_by_arc_length():
    square = np.array([[0, 0], [2, 0], [2, 2], [0, 2]], float)
    pts = resample_polygon(square, 8)  # perimeter 8: one point per unit length
    assert np.allclose(pts, [[0, 0], [1, 0], [2, 0], [2, 1], [2, 2], [1, 2], [0, 2], [0, 1]])


def test_warm_start_shrinks_about_the_centroid():
    c = circle_surface([1.0, -2.0], 0.5, -0.1)
    w = warm_start(c, shrink=0.8)
    assert len(w.vertices) == 9
    assert w.fine().area == pytest.approx(0.64 * c.fine().area, rel=1e-9)  # regular 9-gon resampled = itself
    s = sphere_surface([1.0, 2.0, 3.0], 1.0, -0.1)
    w = warm_start(s, shrink=0.8)
    assert w.fine().volume == pytest.approx(0.512 * s.fine().volume, rel=1e-6)
    assert np.allclose(w.fine().centroid, [1, 2, 3], atol=1e-9)


def test_warm_start_remeshes_a_stretched_bubble_to_a_regular_mesh():
    s = sphere_surface([0.0, 0.0, 0.0], 1.0, -0.1)
    stretched = s.with_vertices(s.vertices * [2.0, 1.0, 0.6])
    w = warm_start(stretched, shrink=0.8)
    assert isinstance(w.control, Mesh) and 30 <= len(w.vertices) <= 60
    v, f = w.vertices, w.control_faces
    edges = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1)
    before = np.linalg.norm(stretched.vertices[f[:, 0]] - stretched.vertices[f[:, 1]], axis=1) \
        if len(stretched.vertices) == len(v) else None
    assert edges.std() / edges.mean() < 0.3  # regular
    assert before is None or edges.std() / edges.mean() < before.std() / before.mean()
    assert 0.3 < w.fine().volume / (0.512 * stretched.fine().volume) < 1.1


# -- the chain --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small():
    """A 3-bubble expanding foam, two subscans of 12 projections, and warm starts near the truth."""
    from bubsub.core.foam.expanding import simulate_expanding

    foam = expanding2d(2, n_bubbles=3, size=4.0, radius_range=(0.4, 0.6))
    g = ScanGeometry.parallel(np.tile(np.linspace(0, np.pi, 12, endpoint=False), 2), pixel_size=6.0 / 150, cols=150)
    scan, _ = simulate_expanding(foam, g, projections_per_subscan=12)
    truth = foam.at(0.25)
    starts = [circle_surface(c, 1.1 * r, -0.1) for c, r in zip(truth.centres, truth.radii)]
    return subscan(scan, subscan_layout(scan), 0), truth, starts


def test_subscan_step_is_picklable_and_keeps_track_ids(small):
    sub, truth, starts = small
    state = BubbleState.from_surfaces([7, 3, 5], starts)
    settings = DynamicSettings(iterations=15, progress=False)
    args = pickle.loads(pickle.dumps((sub, state, settings)))
    res = reconstruct_subscan(*args, index=0, time=0.5)
    res = pickle.loads(pickle.dumps(res))
    assert res.state.ids == (7, 3, 5) and res.report["start"] == "warm" and res.ended == ()
    assert res.report["objective"] < res.report["initial_objective"]
    parts = res.report["seconds_parts"]  # what the subscan's time is made of
    assert set(parts) == {"remesh", "fit", "detect"} and 0 < sum(parts.values()) <= res.report["seconds"]
    assert res.report["new"] == {} and res.report["coalescences"] == []  # every true bubble has its warm start
    assert res.report["evaluations"] >= res.report["iterations"] and res.report["cpu_seconds"] > 0
    for s, r in zip(res.state.surfaces(), truth.radii):
        assert np.sqrt(s.fine().area / np.pi) == pytest.approx(r, rel=0.1)


def test_a_bubble_that_is_not_there_collapses_and_ends_its_track(small):
    sub, _, starts = small
    state = BubbleState.from_surfaces([7, 3, 5, 9], starts + [circle_surface([-1.6, -1.6], 0.25, -0.1)])
    res = reconstruct_subscan(sub, state, DynamicSettings(iterations=15, progress=False))
    assert res.ended == (9,) and res.state.ids == (7, 3, 5)
    assert "collapsed" in res.report["ended"]["9"]


def test_a_diverged_fit_is_flagged_and_keeps_the_last_good_state(small, monkeypatch):
    from bubsub.clients.optimise import levels

    def diverging(*a, **k):
        raise RuntimeError("the objective became NaN")

    monkeypatch.setattr(levels, "fit", diverging)  # the warm start's fit, level by level
    sub, _, starts = small
    state = BubbleState.from_surfaces([7, 3, 5], starts)
    res = reconstruct_subscan(sub, state, DynamicSettings(iterations=15, progress=False, holdout="odd"))
    assert res.report["diverged"] is True and "NaN" in res.report["error"]
    assert res.state is state and res.ended == ()
    assert res.report["holdout_mse"] > 0  # the kept state is still scored


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("dynsim")
    rc = main(["simulate", "--phantom", "expanding2d", "--bubbles", "6", "--det-count", "240", "--subscans", "3",
               "--projections-per-subscan", "16", "--seed", "5", "--out", str(out)])
    assert rc == 0
    return out


@pytest.fixture(scope="module")
def rec(sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("dynrec")
    rc = main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(out), "--holdout", "odd", "--iterations", "30",
               "--voxel-baseline", "--quiet"])
    assert rc == 0
    return out


def test_simulated_dynamic_scan(sim):
    meta = json.loads((sim / "phantom.json").read_text())
    scan = read_scan(sim / "scan.h5")
    assert scan.projections_per_subscan == 16 and scan.n_angles == 48
    assert np.allclose(np.diff(scan.time), 0.01)
    areas = [sum(p.area for p in read_polygons_json(sim / "truth" / f"subscan_{k:04d}.json")) for k in range(3)]
    assert areas[0] < areas[1] < areas[2]  # the foam expands
    assert meta["subscans"] == 3 and len(meta["subscan_times"]) == 3
    # the foam moves during a subscan: the first and last projections of subscan 0 see different liquid squares
    assert not np.allclose(scan.background[0], scan.background[15 - 15 % 2])


def test_reconstruct4d_outputs_and_tracks(sim, rec):
    report = json.loads((rec / "report.json").read_text())
    assert report["engine"] == "local" and report["workers"] == 1
    per = {p["subscan"]: p for p in report["subscans"]}
    assert per[2]["start"] == "cold" and per[1]["start"] == per[0]["start"] == "warm"
    # the cold start's preview voxel, which bubsub analyse takes for the folder's default contact gap
    cold = json.loads((rec / "subscan_0002" / "report.json").read_text())
    assert cold["preview"]["voxel_mm"] > 0 and "preview" not in per[0]
    assert all(p["holdout_mse"] < 1e-3 for p in per.values())
    assert all(0 < p["voxel_holdout_mse"] < 1e-2 for p in per.values())
    with open(rec / "tracks.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["subscan", "time_s", "bubble_id", "centroid_x_mm", "centroid_y_mm", "area_mm2",
                             "perimeter_mm", "equivalent_diameter_mm", "truncated", "area_in_fov_mm2"]
    # every bubble of this foam lies inside the field of view: flagged so, its in-view area its whole area
    assert {r["truncated"] for r in rows} == {"0"}
    assert all(float(r["area_in_fov_mm2"]) == float(r["area_mm2"]) for r in rows)
    with open(rec / "subscan_0001" / "bubbles.csv") as fh:
        assert "truncated" in next(csv.reader(fh))
    ids = {k: {int(r["bubble_id"]) for r in rows if int(r["subscan"]) == k} for k in range(3)}
    assert ids[0] <= ids[1] <= ids[2] and len(ids[2]) == 6
    for name in ("growth.png", "mse.png"):
        assert (rec / name).read_bytes()[:4] == b"\x89PNG"
    # each track follows one true bubble: nearest truth centroid at every subscan is the same
    from bubsub.clients.pipeline.evaluation.evaluate4d import evaluate_dynamic

    score = evaluate_dynamic(rec, sim)
    assert score["right_track_fraction"] == 1.0
    assert score["mean_ddi"] < 0.1
    polys, pid = read_polygons_json(rec / "subscan_0001" / "bubbles.json", with_ids=True)
    assert set(pid) == ids[1]


def test_resume_continues_from_complete_subscans(sim, rec, tmp_path, capsys):
    out = tmp_path / "r"
    shutil.copytree(rec, out)
    shutil.rmtree(out / "subscan_0000")
    with pytest.raises(ValueError, match="--resume"):
        from bubsub.clients.pipeline.reconstruct4d import reconstruct_dynamic

        reconstruct_dynamic(read_scan(sim / "scan.h5"), out, DynamicSettings(iterations=5, progress=False))
    assert main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(out), "--holdout", "odd", "--iterations", "30",
                 "--resume", "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["subscans_complete"] == 3
    old = json.loads((rec / "subscan_0001" / "report.json").read_text())
    new = json.loads((out / "subscan_0001" / "report.json").read_text())
    assert new["seconds"] == old["seconds"]  # kept, not redone
    # the kept subscans' steps are measured again: the redone subscan starts where the uninterrupted run's did
    old, new = (json.loads((d / "subscan_0000" / "report.json").read_text()) for d in (rec, out))
    assert new["initial_objective"] == pytest.approx(old["initial_objective"], rel=1e-3)
    assert main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(out), "--holdout", "even", "--resume",
                 "--quiet"]) == 2  # different settings: refused
    assert main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(out), "--quiet"]) == 2  # neither flag
    assert "--overwrite" in capsys.readouterr().err
    manifest = json.loads((out / "bubsub-outputs.json").read_text())
    assert "subscan_0000/bubbles.json" in manifest["files"] and "tracks.csv" in manifest["files"]


def test_reconstruct4d_bad_inputs(sim, tmp_path, capsys):
    assert main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(tmp_path / "a"), "--subscans", "1:9",
                 "--quiet"]) == 2
    assert "out of bounds" in capsys.readouterr().err
    assert main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(tmp_path / "b"), "--projections-per-subscan",
                 "10", "--quiet"]) == 2
    assert "contradicts" in capsys.readouterr().err


@pytest.fixture(scope="module")
def three():
    """The 3-bubble foam over three subscans of 12 projections, and starts near its last state."""
    from bubsub.core.foam.expanding import simulate_expanding

    foam = expanding2d(2, n_bubbles=3, size=4.0, radius_range=(0.4, 0.6))
    g = ScanGeometry.parallel(np.tile(np.linspace(0, np.pi, 12, endpoint=False), 3), pixel_size=6.0 / 150, cols=150)
    scan, mid = simulate_expanding(foam, g, projections_per_subscan=12)
    truth = foam.at(mid[2])
    return scan, [circle_surface(c, 1.1 * r, -0.1) for c, r in zip(truth.centres, truth.radii)]


def test_a_diverged_subscan_is_kept_flagged_and_the_chain_goes_on(three, tmp_path, monkeypatch):
    from bubsub.clients.optimise import levels
    from bubsub.clients.pipeline.dynamic4d import outputs4d
    from bubsub.clients.pipeline.dynamic4d.chain import run_chain

    scan, starts = three
    layout = subscan_layout(scan)
    real, calls = levels.fit, []

    def nan_in_subscan_1(*a, **k):  # the second fit of the chain (subscan 1) ends with a NaN objective
        calls.append(1)
        res = real(*a, **k)
        if len(calls) == 2:
            res.objective = float("nan")
        return res

    monkeypatch.setattr(levels, "fit", nan_in_subscan_1)  # the warm starts' fits, level by level
    settings = DynamicSettings(iterations=15, progress=False, holdout="odd")
    results, interrupted = run_chain(
        lambda k: subscan(scan, layout, k), [2, 1, 0], settings, start=BubbleState.from_surfaces([7, 3, 5], starts),
        on_result=lambda r: outputs4d.write_subscan(tmp_path, r, 2))
    assert not interrupted and [r.index for r in results] == [2, 1, 0] and len(calls) == 3
    r2, r1, r0 = results
    assert not r2.report["diverged"] and not r0.report["diverged"]
    assert r1.report["diverged"] is True and "nan" in r1.report["error"]
    assert r1.state is r2.state and r1.ended == ()  # kept: the last good state, ids and all
    assert r0.state.ids == (7, 3, 5) and np.isfinite(r0.report["objective"])
    assert r0.report["objective"] < r0.report["initial_objective"]  # the chain went on from subscan 2's bubbles
    assert sorted(outputs4d.complete_subscans(tmp_path)) == [0, 1, 2]
    report = outputs4d.write_summary(tmp_path, results, layout=layout, time_unit="s", settings=settings)
    assert report["totals"]["subscans_diverged"] == 1 and report["totals"]["tracks"] == 3
    assert [p["diverged"] for p in json.loads((tmp_path / "report.json").read_text())["subscans"]] == [
        False, True, False]


def test_projections_per_subscan_that_does_not_divide_runs_the_complete_subscans(three, tmp_path):
    from bubsub.clients.pipeline.reconstruct4d import reconstruct_dynamic

    scan, starts = three
    plain = Scan(data=scan.data, geometry=scan.geometry, bubble_contrast=scan.bubble_contrast,
                 background=scan.background)  # no projections_per_subscan attribute: it must be given
    with pytest.warns(UserWarning, match="does not divide the scan's 36 projections: 2 complete subscans"):
        report = reconstruct_dynamic(plain, tmp_path, DynamicSettings(iterations=3, progress=False),
                                     projections_per_subscan=16, subscans="1:2")
    assert (report["projections_per_subscan"], report["subscans_in_scan"], report["projections_ignored"]) == (16, 2, 4)
    assert [p["subscan"] for p in report["subscans"]] == [1]
    assert sorted(p.name for p in tmp_path.glob("subscan_*")) == ["subscan_0001"]


def test_ctrl_c_leaves_finished_subscans_complete(sim, tmp_path, monkeypatch):
    from bubsub.clients.pipeline import reconstruct4d

    real = reconstruct4d.reconstruct_subscan
    calls = {"n": 0}

    def interrupted(*a, **k):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(reconstruct4d, "reconstruct_subscan", interrupted)  # the step the chain driver runs
    out = tmp_path / "c"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = main(["reconstruct4d", str(sim / "scan.h5"), "--out", str(out), "--iterations", "10", "--quiet"])
    assert rc == 130
    assert sorted(p.name for p in out.iterdir() if p.name.startswith("subscan")) == ["subscan_0002"]
    assert (out / "subscan_0002" / "report.json").is_file()
    assert json.loads((out / "report.json").read_text())["interrupted"] is True


# -- the voxel baseline -----------------------------------------------------------------------
class _Dense:
    """A matrix as a solver operator."""

    def __init__(self, A, shape):
        self.A, self.shape, self.proj_shape = A.astype(np.float32), shape, (A.shape[0],)

    def forward(self, x):
        return self.A @ x.ravel()

    def adjoint(self, y):
        return (self.A.T @ y).reshape(self.shape)


def test_pgd_bb_reaches_the_nonnegative_least_squares_solution():
    from scipy.optimize import nnls

    from bubsub.core.voxel.solvers import pgd_bb

    rng = np.random.default_rng(1)
    A = rng.normal(size=(60, 20)) + 2 * np.eye(60, 20)
    b = A @ np.where(rng.uniform(size=20) < 0.5, 0.0, rng.uniform(0.5, 2, 20)) + 0.1 * rng.normal(size=60)
    want, _ = nnls(A, b)
    assert (want == 0).any()  # the constraint is active somewhere
    op = _Dense(A, (4, 5))
    got = pgd_bb(op, b.astype(np.float32), 200)
    assert got.min() >= 0
    assert np.allclose(got.ravel(), want, atol=2e-3)
    free = pgd_bb(op, b.astype(np.float32), 200, nonneg=False)
    assert np.allclose(free.ravel(), np.linalg.lstsq(A, b, rcond=None)[0], atol=2e-3)
    # 30 iterations (the paper's baseline) already get most of the way
    f = lambda x: np.sum((A @ x.ravel() - b) ** 2)
    assert f(pgd_bb(op, b.astype(np.float32), 30)) < f(np.zeros(20)) * 0.05


def test_pgd_bb_with_an_upper_bound_reaches_the_box_constrained_solution():
    from scipy.optimize import lsq_linear

    from bubsub.core.voxel.solvers import pgd_bb

    rng = np.random.default_rng(3)
    A = rng.normal(size=(60, 20)) + 2 * np.eye(60, 20)
    truth = np.where(rng.uniform(size=20) < 0.4, 0.0, 1.0)  # a bubble image: 0 or the contrast
    b = A @ truth + 0.6 * rng.normal(size=60)
    want = lsq_linear(A, b, bounds=(0.0, 1.0), tol=1e-12).x
    assert (want >= 1 - 1e-9).any() and (want <= 1e-9).any()  # both bounds active
    op = _Dense(A, (4, 5))
    got = pgd_bb(op, b.astype(np.float32), 300, upper=1.0)
    assert got.min() >= 0 and got.max() <= 1
    assert np.allclose(got.ravel(), want, atol=2e-3)
    with pytest.raises(ValueError, match="upper"):
        pgd_bb(op, b.astype(np.float32), 10, upper=-1.0)


def test_an_upper_bound_goes_only_to_the_box_constrained_method():
    from bubsub.core import ScanGeometry
    from bubsub.core.voxel.astra2d import reconstruct_2d

    g = ScanGeometry.parallel(np.linspace(0, np.pi, 12, endpoint=False), cols=32)
    sino = np.ones(g.shape, dtype=np.float32)
    image = reconstruct_2d("bb", sino, g, (32, 32), (-16, 16, -16, 16), iterations=5, nonneg=True, upper=0.01,
                           backend="numpy")
    assert image.max() <= 0.01 + 1e-7
    for method, backend in (("sirt", "numpy"), ("sirt", "astra"), ("fbp", "numpy")):
        with pytest.raises(ValueError, match="only taken by method 'bb'"):
            reconstruct_2d(method, sino, g, (32, 32), (-16, 16, -16, 16), iterations=5, upper=0.01, backend=backend)


def test_track_check_catches_swapped_ids(sim, rec, tmp_path):
    from bubsub.clients.pipeline.evaluation.evaluate4d import evaluate_dynamic

    out = tmp_path / "swapped"
    shutil.copytree(rec, out)
    path = out / "subscan_0000" / "bubbles.json"
    doc = json.loads(path.read_text())
    a, b = doc["bubbles"][0]["id"], doc["bubbles"][1]["id"]
    doc["bubbles"][0]["id"], doc["bubbles"][1]["id"] = b, a
    path.write_text(json.dumps(doc))
    score = evaluate_dynamic(out, sim)
    assert score["rows"] == 18 and score["right_track_fraction"] == pytest.approx(16 / 18)


def test_fig6_quick(tmp_path, capsys):
    assert main(["experiment", "fig6", "--quick", "--out", str(tmp_path), "--quiet"]) == 0
    assert re.search(r"median warm / cold subscan time: \d+\.\d{3} \(wall\), \d+\.\d{3} \(CPU\)",
                     capsys.readouterr().out)
    summary = json.loads((tmp_path / "fig6.json").read_text())
    with open(tmp_path / "fig6.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted({r["method"] for r in rows}) == ["bb", "bubsub", "sirt"] and len(rows) == 6
    ours = [r for r in rows if r["method"] == "bubsub"]
    assert [r["start"] for r in ours] == ["warm", "cold"] and all(int(r["iterations"]) > 0 for r in ours)
    assert summary["warm_to_cold_cpu_time"] == pytest.approx(  # of the table's six significant digits
        float(ours[0]["cpu_seconds"]) / float(ours[1]["cpu_seconds"]), rel=2e-5)
    assert (tmp_path / "fig6.csv-metadata.json").is_file()
    assert summary["mean_ddi"]["bubsub"] < 0.5 * summary["mean_ddi"]["sirt"]
    assert summary["mean_holdout_mse"]["bubsub"] < summary["mean_holdout_mse"]["bb"]
    assert summary["right_track_fraction"] == 1.0
    for name in ("fig6.png", "fig7.png"):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"


def test_a_warm_fit_stops_at_the_objective_plateau(small):
    sub, truth, starts = small
    state = BubbleState.from_surfaces([0, 1, 2], starts)
    # the plateau test at 0.1 % (the default, 0.2 %, is set on noisy scans: bubsub bench dynamic, docs/dynamic.md)
    early = reconstruct_subscan(sub, state, DynamicSettings(iterations=80, warm_rtol=1e-3, progress=False))
    assert early.report["stop_reason"] == "objective plateau" and early.report["iterations"] < 80
    full = reconstruct_subscan(sub, state, DynamicSettings(iterations=early.report["iterations"] + 10,
                                                           warm_rtol=0, progress=False))
    assert full.report["iterations"] > early.report["iterations"]
    # the iterations saved would have lowered the objective by well under a percent
    assert early.report["objective"] <= 1.01 * full.report["objective"]
    for s, r in zip(early.state.surfaces(), truth.radii):
        assert np.sqrt(s.fine().area / np.pi) == pytest.approx(r, rel=0.1)


def test_dynamic_settings_hold_every_static_setting():
    import dataclasses

    from bubsub.clients.pipeline.dynamic4d.chain import _static_settings
    from bubsub.clients.pipeline.reconstruct import ReconstructionSettings

    settings = DynamicSettings(iterations=7, separation=0.5, topology_rounds=1, shrink=0.9)
    assert settings.static == ReconstructionSettings(iterations=7, separation=0.5, topology_rounds=1)
    assert (settings.iterations, settings.separation, settings.shrink) == (7, 0.5, 0.9)
    # every field of the static settings is read through, so a new one reaches the 4D cold start
    for f in dataclasses.fields(ReconstructionSettings):
        assert getattr(settings, f.name) == getattr(settings.static, f.name)
    cold = _static_settings(settings)
    assert cold.refine is False and cold.separation == 0.5 and cold.topology_rounds == 1
    assert pickle.loads(pickle.dumps(settings)) == settings
    assert dataclasses.replace(settings, warm_rtol=0.0).static == settings.static
    with pytest.raises(TypeError, match="unknown settings"):
        DynamicSettings(iteration=7)
    with pytest.raises(ValueError, match="non-negative integer"):
        DynamicSettings(iterations=-1)
    with pytest.raises(AttributeError):
        settings.no_such_setting
