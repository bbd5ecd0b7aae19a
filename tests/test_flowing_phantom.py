"""The flowing, coarsening foam column: its events happen as declared, and its scan shows the foam at each time."""

import csv
import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bubsub.core.foam.ellipsoids import contact_function, ellipsoid_mesh, shape_matrices
from bubsub.core.foam.flowing import flowing_foam
from bubsub.core.foam.flowing_scan import projection_times, simulate_flowing

#: A tiny column: 32 x 96 pixels of 48 um, about 30 bubbles in view, 4 subscans.
TINY = dict(rows=32, cols=96, pixel_size=0.048, subscans=4, coalescences=1)


@pytest.fixture(scope="module")
def foam():
    return flowing_foam(30, seed=1, **TINY)


def test_vanishing_bubbles_shrink_to_nothing_with_r2_linear(foam):
    vanish = np.flatnonzero(np.isfinite(foam.vanish_time))
    assert len(vanish) == round(0.12 * len(foam.column.centres))
    # the smallest bubbles vanish
    assert foam.column.volumes[vanish].max() <= np.sort(foam.column.volumes)[len(vanish) - 1] + 1e-15
    for b in vanish[:4]:
        tv = foam.vanish_time[b]
        assert 0 < tv < foam.duration
        r0 = foam.column.axes[b]
        for f in (0.25, 0.5, 0.9):
            st = foam.at(f * tv)
            np.testing.assert_allclose(st.axes[st.ids == b][0], r0 * np.sqrt(1 - f), rtol=1e-9)
        assert b not in foam.at(tv).ids
        assert foam.at(tv * (1 - 1e-6)).axes[foam.at(tv * (1 - 1e-6)).ids == b].max() < 1e-2 * r0.max()


def test_coalescence_conserves_volume_and_gives_a_new_id(foam):
    (m,) = foam.merges
    a, b = m["parents"]
    before, after = foam.at(m["time"] - 1e-9), foam.at(m["time"])
    vol = dict(zip(before.ids, before.volumes))
    assert a in vol and b in vol and m["child"] not in before.ids
    assert a not in after.ids and b not in after.ids
    child = after.volumes[after.ids == m["child"]][0]
    assert child == pytest.approx(vol[a] + vol[b], rel=1e-9)
    assert m["child"] >= len(foam.column.centres)
    # the parents touched (contact function close to 1) and the child sits where they were, volume-weighted
    s = shape_matrices(foam.column.axes[[a, b]], foam.column.rotations[[a, b]])
    assert contact_function(s[:1], s[1:], (foam.column.centres[b] - foam.column.centres[a])[None])[0] < 1.3
    centre = (vol[a] * before.centres[before.ids == a][0] + vol[b] * before.centres[before.ids == b][0]) / (
        vol[a] + vol[b])
    np.testing.assert_allclose(after.centres[after.ids == m["child"]][0], centre, atol=1e-12)


def test_gas_is_conserved_and_bubbles_never_overlap(foam):
    total = foam.at(0).volumes.sum()
    assert foam.gas_kept == 1.0
    touching = []
    for t in np.linspace(0, foam.duration, 9):
        st = foam.at(t)
        assert st.volumes.sum() == pytest.approx(total, rel=1e-9)
        assert len(np.unique(st.ids)) == len(st.ids)
        s = shape_matrices(st.axes, st.rotations)
        i, j = cKDTree(st.centres).query_pairs(2 * st.axes.max(), output_type="ndarray").T
        f = contact_function(s[i], s[j], st.centres[j] - st.centres[i])
        assert f.min() >= 1.0 - 1e-9
        touching.append(int(np.sum(f < 1.02**2)))
    assert touching[-1] > touching[0]  # growers fill their films and come into contact


def test_plug_flow_moves_centroids_by_the_flow(foam):
    px = foam.column.pixel_size
    a, b = foam.at(0.5), foam.at(1.5)
    common = np.intersect1d(a.ids, b.ids)
    ca = {i: c for i, c in zip(a.ids, a.centres)}
    cb = {i: c for i, c in zip(b.ids, b.centres)}
    # the centroid of each truth mesh (an independent construction) moves up 4 pixels per subscan
    for i in common[:10]:
        ma = ellipsoid_mesh(ca[i], a.axes[a.ids == i][0], a.rotations[a.ids == i][0], -0.1, 2)
        mb = ellipsoid_mesh(cb[i], b.axes[b.ids == i][0], b.rotations[b.ids == i][0], -0.1, 2)
        np.testing.assert_allclose(np.asarray(mb.centroid) - np.asarray(ma.centroid), [0, 0, 4 * px], atol=1e-9)


def test_projections_show_the_foam_at_their_own_time(foam):
    from bubsub.core.projection.projector import MeshProjector

    scan = simulate_flowing(foam, projections_per_subscan=8, photons=None, supersampling=2)
    assert scan.data.shape == (32, 32, 96) and scan.projections_per_subscan == 8
    angles = np.degrees(np.arctan2(scan.geometry.vectors[:, 0], -scan.geometry.vectors[:, 1]))
    assert np.allclose(np.diff(np.unwrap(np.radians(angles))), np.pi / 8)  # continuous rotation
    t = projection_times(32, 8)
    for j in (3, 20):
        st = foam.at(t[j])
        vis = st.select(st.visible)
        meshes = [ellipsoid_mesh(c, a, r, foam.column.contrast, 4) for c, a, r in
                  zip(vis.centres, vis.axes, vis.rotations)]
        proj = MeshProjector(scan.geometry[j:j + 1], supersampling=2)
        want = proj.forward(meshes)[0] + scan.background[j]
        bubbles = np.abs(want - scan.background[j]) > 1e-3
        err = np.abs(scan.data[j] - want)[bubbles]
        assert np.percentile(err, 99) < 0.02 * np.abs(want - scan.background[j]).max()
        # a subscan later the foam has moved on: the same view of the later foam differs much more
        later = foam.at(t[j] + 1.0)
        lv = later.select(later.visible)
        other = proj.forward([ellipsoid_mesh(c, a, r, foam.column.contrast, 2) for c, a, r in
                              zip(lv.centres, lv.axes, lv.rotations)])[0] + scan.background[j]
        assert np.abs(scan.data[j] - other)[bubbles].mean() > 5 * err.mean()


def test_cli_writes_truth_per_subscan_with_ids_and_events(tmp_path):
    from bubsub.clients.cli.main import main
    from bubsub.core.io.meshio import read_ply

    out = tmp_path / "flow"
    assert main(["simulate", "--phantom", "flowing3d", "--det-count", "96", "--bubbles", "30", "--subscans", "4",
                 "--projections-per-subscan", "8", "--coalescences", "1", "--seed", "1", "--out", str(out)]) == 0
    meta = json.loads((out / "phantom.json").read_text())
    assert meta["phantom"] == "flowing3d" and meta["subscans"] == 4 and meta["projections_per_subscan"] == 8
    assert meta["flowing"]["flow_px_per_subscan"] == 4.0
    truth = {}
    for k in range(4):
        meshes, ids = read_ply(out / "truth" / f"subscan_{k:04d}.ply", with_ids=True)
        with open(out / "truth" / f"subscan_{k:04d}.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
        assert len(set(ids)) == len(ids) == len(rows)
        assert [int(r["id"]) for r in rows] == list(ids)
        vol = np.array([float(r["volume_mm3"]) for r in rows])
        np.testing.assert_allclose([m.volume for m in meshes], vol, rtol=2e-3)  # meshes enclose the exact volume
        truth[k] = set(ids)
    with open(out / "events.csv", newline="") as fh:
        events = list(csv.DictReader(fh))
    kinds = {e["event"] for e in events}
    assert {"enter", "exit", "vanish", "coalesce"} <= kinds
    for e in events:
        k, b = int(e["subscan"]), int(e["id"])
        if not 0 < k < 4:
            continue
        if e["event"] == "enter":
            assert b not in truth[k - 1] and b in truth[k]
        elif e["event"] in ("exit", "vanish") and e["in_fov"] == "1":
            assert b in truth[k - 1] and b not in truth[k]
        elif e["event"] == "coalesce":
            a, c = (int(x) for x in e["parents"].split(";"))
            assert {a, c} <= truth[k - 1] and b in truth[k] and not ({a, c} & truth[k])
    # the flags refuse the other phantoms
    assert main(["simulate", "--phantom", "foam2d", "--flow", "2", "--out", str(tmp_path / "x")]) != 0
