"""``bubsub analyse`` end to end on tiny reconstruct and reconstruct4d folders, and its refusals."""

import csv
import json

import numpy as np
import pytest
from trimesh.triangles import closest_point

from bubsub.clients.cli.main import main
from bubsub.clients.pipeline.dynamic4d import outputs4d
from bubsub.clients.pipeline.dynamic4d.chain import BubbleState, SubscanResult
from bubsub.clients.pipeline.results.outputs import write_outputs
from bubsub.clients.pipeline.reconstruct import Reconstruction
from bubsub.core.io.atomic import atomic_write_text
from bubsub.core.io.meshio import read_ply
from bubsub.core.projection.subdivision import circle_surface, sphere_surface
from test_analysis_dynamics import t1_centres

C = -0.1
FOV = {"radius": 2.4, "half_height": 1.2, "margin": 0.05}


def brute_force_gap(a, b):
    """Least distance from the vertices of either mesh near the other to all of the other's triangles."""
    best = np.inf
    for p, q in ((a, b), (b, a)):
        near = p.vertices[np.linalg.norm(p.vertices - q.centroid, axis=1) < np.linalg.norm(q.vertices - q.centroid,
                                                                                            axis=1).max() + 0.05]
        tri = q.vertices[np.asarray(q.faces)]
        pts, tris = np.repeat(near, len(tri), axis=0), np.tile(tri, (len(near), 1, 1))
        best = min(best, np.linalg.norm(pts - closest_point(tris, pts), axis=1).min())
    return best


def rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def rec3d(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rec3d")
    surfaces = [sphere_surface((-0.455, 0, 0), 0.45, C, levels=3), sphere_surface((0.465, 0, 0), 0.45, C, levels=3),
                sphere_surface((0, 1.2, 0.1), 0.4, C, levels=3), sphere_surface((0.3, -1.0, 1.1), 0.4, C, levels=3)]
    write_outputs(folder, Reconstruction(surfaces, {"dimension": 3, "field_of_view_mm": FOV}, ids=[10, 20, 30, 40]))
    return folder


def test_analyse_a_reconstruct_folder(rec3d, tmp_path, capsys):
    out = tmp_path / "an"
    assert main(["analyse", str(rec3d), "--out", str(out), "--quiet"]) == 0
    assert "4 bubbles (1 cut by the field of view), 1 contacts" in capsys.readouterr().out
    bubbles = rows(out / "bubbles.csv")
    assert [int(r["id"]) for r in bubbles] == [10, 20, 30, 40]  # the bubble_id of bubbles.ply
    by_id = {int(r["id"]): r for r in bubbles}
    assert [by_id[i]["coordination"] for i in (10, 20, 30, 40)] == ["1", "1", "0", "0"]
    assert by_id[40]["truncated"] == "1" and by_id[40]["volume_mm3"] == by_id[40]["sphericity"] == ""
    rec_rows = {int(r["id"]): r for r in rows(rec3d / "bubbles.csv")}
    assert float(by_id[40]["volume_in_fov_mm3"]) == pytest.approx(float(rec_rows[40]["volume_in_fov_mm3"]))
    assert float(by_id[10]["volume_mm3"]) == pytest.approx(float(rec_rows[10]["volume_mm3"]))
    assert float(by_id[10]["sphericity"]) > 0.999
    (contact,) = rows(out / "contacts.csv")
    assert (contact["id_a"], contact["id_b"]) == ("10", "20")
    # to the table's six significant digits
    assert float(contact["gap_mm"]) == pytest.approx(brute_force_gap(*read_ply(rec3d / "bubbles.ply")[:2]), rel=5e-6)
    assert float(contact["branch_x_mm"]) == pytest.approx(0.92, abs=1e-3)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["contact_gap_mm"] == pytest.approx(2 * 2.4 / 160)  # one voxel of the default preview
    gas = sum(float(r["volume_in_fov_mm3"]) for r in bubbles)
    assert summary["liquid_fraction"] == pytest.approx(1 - gas / (np.pi * 2.4 ** 2 * 2.4), abs=0.002)
    shells = rows(out / "regions_shells.csv")
    assert sum(int(r["bubbles"]) for r in shells) == 4 and sum(int(r["contacts"]) for r in shells) == 1
    meta = json.loads((out / "bubbles.csv-metadata.json").read_text())
    units = {c["name"]: c.get("unit") for c in meta["tableSchema"]["columns"]}
    assert units["volume_mm3"] == "mm^3" and units["shape_eigenvalue_1_mm2"] == "mm^2"
    for name in ("sizes.png", "sphericity.png", "coordination.png", "liquid_fraction.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    manifest = json.loads((out / "bubsub-outputs.json").read_text())
    assert manifest["command"] == "analyse" and "contacts.csv" in manifest["files"]
    # a smaller gap finds no contact; an earlier analysis is replaced only with --overwrite
    assert main(["analyse", str(rec3d), "--out", str(out), "--quiet"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main(["analyse", str(rec3d), "--out", str(out), "--quiet", "--overwrite", "--contact-gap", "0.005",
                 "--grid", "2", "1", "1", "--shells", "3", "--no-pictures", "--radius", "2.0"]) == 0
    assert rows(out / "contacts.csv") == [] and len(rows(out / "regions_shells.csv")) == 3
    shells = rows(out / "regions_shells.csv")  # the narrower sample's cylinder, in three equal-width shells
    assert [float(r["region_volume_mm3"]) for r in shells] == pytest.approx(
        np.pi * np.diff(np.linspace(0, 2.0, 4) ** 2) * 2.4, rel=2e-3)
    assert not (out / "sizes.png").exists()  # the earlier run's pictures are not left behind
    assert len(rows(out / "regions_grid.csv")) == 2


def write_rec4d(folder, cold_voxel=None):
    """Three subscans: the T1 of four bubbles (0 -> 1), a growing bubble 5, bubble 6 gone at the last; with
    ``cold_voxel`` the last one's report gives its preview's voxel (the cold start of ``reconstruct4d``)."""
    times = [0.0, 2.0, 4.0]
    results = []
    for k, t in enumerate(times):
        centres = t1_centres(after=k > 0)
        surfaces = {i: sphere_surface(c, 0.4, C, levels=2) for i, c in centres.items()}
        surfaces[5] = sphere_surface((1.2, 1.2, 0.0), 0.3 + 0.03 * k, C, levels=2)
        if k < 2:
            surfaces[6] = sphere_surface((-1.2, 1.2, 0.0), 0.3 - 0.05 * k, C, levels=2)
        ids = sorted(surfaces)
        state = BubbleState.from_surfaces(ids, [surfaces[i] for i in ids])
        report = {"subscan": k, "time": t, "bubbles": len(ids), "field_of_view_mm": FOV}
        if cold_voxel and k == len(times) - 1:
            report["preview"] = {"voxel_mm": cold_voxel, "shape": [8, 8, 8], "finer_for_bubbles": True}
        result = SubscanResult(k, t, state, (), report)
        outputs4d.write_subscan(folder, result, 3)
        results.append(result)
    outputs4d.write_tracks(folder / "tracks.csv", results, "s")
    atomic_write_text(folder / "report.json", json.dumps({"time_unit": "s"}))


def test_analyse_a_reconstruct4d_folder(tmp_path, capsys):
    rec, out = tmp_path / "rec4d", tmp_path / "an4d"
    write_rec4d(rec)
    assert main(["analyse", str(rec), "--out", str(out), "--contact-gap", "0.03"]) == 0
    printed = capsys.readouterr().out
    assert "subscan 2 (3 of 3)" in printed and "1 T1 events" in printed
    assert "in the cylinder of the field of view" in printed
    # reconstruct4d's tracks.csv has its sidecar, describing every column
    meta = json.loads((rec / "tracks.csv-metadata.json").read_text())
    assert [c["name"] for c in meta["tableSchema"]["columns"]] == list(rows(rec / "tracks.csv")[0])
    (t1,) = rows(out / "t1_events.csv")
    assert [t1[k] for k in ("lost_a", "lost_b", "gained_c", "gained_d", "subscan_before", "subscan_after")] == \
        ["1", "2", "3", "4", "0", "1"]
    assert float(t1["time_s_after"]) == 2.0
    events = rows(out / "track_events.csv")
    assert [(e["kind"], e["bubble_id"], e["subscan_before"]) for e in events] == [("disappearance", "6", "1")]
    bubbles = rows(out / "bubbles.csv")
    assert {"subscan", "time_s"} <= set(bubbles[0]) and len(bubbles) == 6 + 6 + 5
    vol = {(int(r["subscan"]), int(r["id"])): float(r["volume_mm3"]) for r in bubbles}
    rates = {(int(r["subscan"]), int(r["bubble_id"])): r for r in rows(out / "rates.csv")}
    # central and one-sided differences, of volumes written to six significant digits
    assert float(rates[1, 5]["volume_rate_mm3_per_s"]) == pytest.approx((vol[2, 5] - vol[0, 5]) / 4.0, rel=1e-4)
    assert float(rates[0, 5]["volume_rate_mm3_per_s"]) == pytest.approx((vol[1, 5] - vol[0, 5]) / 2.0, rel=1e-4)
    assert int(rates[1, 3]["coordination"]) == 3 and int(rates[0, 3]["coordination"]) == 2
    summary = json.loads((out / "summary.json").read_text())
    assert summary["t1_events"] == 1 and summary["disappearances"] == 1 and summary["subscans"] == 3
    assert summary["growth_law"]["points"] == len(rates)
    sizes = rows(out / "sizes.csv")
    assert [int(s["bubbles"]) for s in sizes] == [6, 6, 5]
    meta = json.loads((out / "rates.csv-metadata.json").read_text())
    assert {c["name"]: c.get("unit") for c in meta["tableSchema"]["columns"]}["volume_rate_mm3_per_s"] == "mm^3/s"
    for name in ("growth_law.png", "t1_map.png", "sizes.png", "liquid_fraction.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_input_is_refused_with_a_message(rec3d, tmp_path, capsys):
    out = str(tmp_path / "out")

    def refused(args, words):
        assert main(["analyse", *args]) == 2
        err = capsys.readouterr().err
        assert words in err, err
        assert not (tmp_path / "out").exists()

    refused([str(tmp_path / "missing"), "--out", out], "does not exist")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("not a reconstruction")
    refused([str(empty), "--out", out], "is not the output of bubsub reconstruct")
    refused([str(rec3d), "--out", out, "--contact-gap", "-0.02"], "must be positive")
    refused([str(rec3d), "--out", out, "--contact-gap", "nan"], "must be positive")
    refused([str(rec3d), "--out", str(rec3d)], "not the reconstruction's folder")
    flat = tmp_path / "rec2d"
    flat.mkdir()
    (flat / "bubbles.json").write_text('{"bubbles": []}')
    refused([str(flat), "--out", out], "2D reconstruction")
    refused([str(rec3d / "bubbles.ply"), "--out", out], "is a file")


def test_the_default_contact_gap_is_the_voxel_the_preview_used():
    from bubsub.clients.analysis import default_contact_gap

    fov = {"radius": 2.4}
    assert default_contact_gap({"field_of_view_mm": fov}) == pytest.approx(2 * 2.4 / 160)  # the default preview
    assert default_contact_gap({"field_of_view_mm": fov, "settings": {"voxel_size": 0.02}}) == 0.02  # asked for
    # a preview made finer for small bubbles (.pipeline.preview.voxel_for_bubbles) says so in the report
    assert default_contact_gap({"field_of_view_mm": fov, "settings": {"voxel_size": None},
                                "preview": {"voxel_mm": 0.0181, "finer_for_bubbles": True}}) == 0.0181
    with pytest.raises(ValueError, match="no field of view"):
        default_contact_gap({"settings": {}})


def test_a_4d_folders_default_contact_gap_is_its_cold_starts_preview_voxel(tmp_path):
    from bubsub.clients.analysis import analyse

    plain, cold = tmp_path / "plain", tmp_path / "cold"
    write_rec4d(plain)
    write_rec4d(cold, cold_voxel=0.021)
    assert analyse(plain).summary["contact_gap_mm"] == pytest.approx(2 * FOV["radius"] / 160)
    assert analyse(cold).summary["contact_gap_mm"] == pytest.approx(0.021)  # the warm subscans have no preview


def test_a_2d_reconstruct4d_folder_is_refused_as_2d(tmp_path, capsys):
    """2D foams are not analysed: a 2D reconstruct4d folder says so in one line (not that no subscan is complete)."""
    rec, out = tmp_path / "rec2d4d", tmp_path / "an"
    results = []
    for k in range(2):
        surfaces = [circle_surface((-0.6, 0.0), 0.4, C), circle_surface((0.6, 0.1 * k), 0.35, C)]
        state = BubbleState.from_surfaces([0, 1], surfaces)
        results.append(SubscanResult(k, float(k), state, (), {"subscan": k, "time": float(k), "bubbles": 2}))
        outputs4d.write_subscan(rec, results[-1], 2)
    outputs4d.write_tracks(rec / "tracks.csv", results, "s")
    assert main(["analyse", str(rec), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "2D reconstruct4d folder" in err and "not analysed" in err and "no complete" not in err
    assert len(err.splitlines()) == 1 and not out.exists()


def test_a_4d_folder_is_analysed_on_one_grid_for_all_subscans(tmp_path):
    """Bubbles doubling in size would give each subscan its own default grid; one grid lets a cell be followed."""
    from bubsub.clients.analysis import analyse

    rec = tmp_path / "grow"
    centres = [(-1.0, -1.0, 0.0), (1.0, -1.0, 0.0), (-1.0, 1.0, 0.0), (1.0, 1.0, 0.0)]
    results = []
    for k, r in enumerate((0.2, 0.3, 0.45)):
        state = BubbleState.from_surfaces([0, 1, 2, 3], [sphere_surface(c, r * (1 + 0.02 * i), C, levels=2)
                                                             for i, c in enumerate(centres)])
        results.append(SubscanResult(k, float(k), state, (), {"subscan": k, "time": float(k), "bubbles": 4,
                                                              "field_of_view_mm": FOV}))
        outputs4d.write_subscan(rec, results[-1], 3)
    outputs4d.write_tracks(rec / "tracks.csv", results, "s")
    result = analyse(rec, contact_gap=0.03)
    cells = {}
    for row in result.tables["grid"]:
        cells.setdefault(row["subscan"], []).append(
            tuple(row[c] for c in ("cell_x", "cell_y", "cell_z", "x_lo_mm", "x_hi_mm", "z_lo_mm", "z_hi_mm")))
    assert cells[0] == cells[1] == cells[2]
    # sized from the median radius of all subscans' bubbles (0.3 mm): cells about three diameters wide
    assert result.summary["grid"] == [3, 3, 1] and len(cells[0]) == 9
    gas = {s: sum(r["gas_volume_mm3"] for r in result.tables["grid"] if r["subscan"] == s) for s in cells}
    assert gas[2] == pytest.approx(sum(4 / 3 * np.pi * (0.45 * (1 + 0.02 * i)) ** 3 for i in range(4)), rel=0.01)


def test_reconstruct_and_analyse_tables_give_a_bubble_the_same_columns_and_values(rec3d, tmp_path):
    out = tmp_path / "an"
    assert main(["analyse", str(rec3d), "--out", str(out), "--quiet", "--no-pictures"]) == 0
    ours, theirs = rows(out / "bubbles.csv"), rows(rec3d / "bubbles.csv")
    common = [c for c in theirs[0] if c in ours[0]]
    # every measured column of reconstruct's table, under the same name (the rest are the analysis' own)
    assert set(theirs[0]) - set(common) <= {"unobserved_control_vertices"}
    assert "equivalent_diameter_mm" in common and "surface_area_mm2" in common
    for a, b in zip(ours, theirs):
        assert {c: a[c] for c in common} == {c: b[c] for c in common}  # the same cells, to the digit
    # a near-ball: its area is that of the ball of its volume
    ball = next(r for r in ours if r["id"] == "10")
    assert float(ball["surface_area_mm2"]) == pytest.approx(np.pi * float(ball["equivalent_diameter_mm"]) ** 2,
                                                            rel=5e-4)
    for name in ("bubbles", "contacts", "regions_grid"):
        meta = json.loads((out / f"{name}.csv-metadata.json").read_text())
        assert meta["null"] == "" and "nan" not in (out / f"{name}.csv").read_text().lower()
    meta = {c["name"]: c["dc:description"] for c in
            json.loads((out / "bubbles.csv-metadata.json").read_text())["tableSchema"]["columns"]}
    theirs_meta = {c["name"]: c["dc:description"] for c in
                   json.loads((rec3d / "bubbles.csv-metadata.json").read_text())["tableSchema"]["columns"]}
    assert all(meta[c] == theirs_meta[c] for c in common)  # in the same words
