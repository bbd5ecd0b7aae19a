"""bubsub evaluate writes evaluation.json and evaluation.png, matches bubbles one by one and scores 4D folders.

The reconstructions are the simulations' own truth with known changes (ids renumbered, one bubble shrunk
about its centroid by 0.9, one dropped, one spurious disc or ball added where there is no gas), so the
expected scores follow from geometry: the shrunk bubble's IoU is 0.9^2 (0.9^3 in 3D), its size error
-19 % (-27.1 %) and its equivalent diameter's -10 %; the DDI is the one of these areas.
"""

import json
import shutil

import numpy as np
import pytest

from bubsub.clients.cli import main
from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir
from bubsub.clients.pipeline.results.outputs import MANIFEST, earlier_outputs
from bubsub.core import Mesh, Polygon
from bubsub.core.io.meshio import read_ply, read_polygons_json, write_ply, write_polygons_json

SHRINK = 0.9


def _shrunk(item):
    c = np.asarray(item.centroid)
    v = c + SHRINK * (item.vertices - c)
    return Polygon(v, item.attenuation) if isinstance(item, Polygon) else Mesh(v, item.faces, item.attenuation)


def _free_spot(truth, extent, radius):
    """A centre at least ``radius`` + 0.1 mm from every true bubble's vertices, inside the grid."""
    pts = np.concatenate([t.vertices for t in truth])
    rng = np.random.default_rng(5)
    lo, hi = np.array(extent[0::2]) + radius + 0.1, np.array(extent[1::2]) - radius - 0.1
    for _ in range(20000):
        c = rng.uniform(lo, hi)
        if np.min(np.linalg.norm(pts - c, axis=1)) > radius + 0.1 and not any(
                np.linalg.norm(c - np.asarray(t.centroid)) < 3 * t.equivalent_radius for t in truth):
            return c
    raise AssertionError("no free spot")


def _altered(truth, extent, ndim):
    """``(items, ids)``: truth with bubble 0 shrunk, bubble 1 dropped and a spurious bubble; ids 100 + k."""
    from bubsub.core import circle_surface, sphere_surface

    c = _free_spot(truth, extent, 0.3)
    spurious = (circle_surface(c, 0.3, -0.1, control=64, levels=0) if ndim == 2
                else sphere_surface(c, 0.3, -0.1, control=162, levels=1)).fine()
    items = [_shrunk(truth[0])] + truth[2:] + [spurious]
    ids = [100] + [100 + k for k in range(2, len(truth))] + [999]
    return items, ids


def _simulated_and_altered(root, ndim):
    """``(simulation folder, reconstruction folder, truth)``: a small simulated foam and its :func:`_altered`
    truth written as the reconstruction's bubbles."""
    sim, rec = root / "sim", root / "rec"
    args = (["--phantom", "foam2d", "--det-count", "200", "--angles", "6", "--bubbles", "12", "--seed", "2"]
            if ndim == 2 else ["--phantom", "foam3d", "--det-count", "64", "--angles", "8", "--bubbles", "6"])
    assert main(["simulate", *args, "--out", str(sim)]) == 0
    meta = json.loads((sim / "phantom.json").read_text())
    truth = (read_polygons_json if ndim == 2 else read_ply)(sim / meta["truth"])
    rec.mkdir()
    items, ids = _altered(truth, meta["grid_extent"], ndim)
    (write_polygons_json if ndim == 2 else write_ply)(rec / f"bubbles.{'json' if ndim == 2 else 'ply'}", items, ids)
    return sim, rec, truth


@pytest.fixture(scope="module")
def static2d(tmp_path_factory):
    sim, rec, truth = _simulated_and_altered(tmp_path_factory.mktemp("ev2d"), 2)
    report = {"dimension": 2, "field_of_view_mm": {"radius": 20.0, "half_height": 0.0}, "final_objective": 1.5,
              "iterations": 7, "stop_reason": "converged", "holdout_mse": 1e-4}
    (rec / "report.json").write_text(json.dumps(report))
    (rec / MANIFEST).write_text(json.dumps({"bubsub": "test", "command": "reconstruct",
                                            "files": ["bubbles.json", "report.json"]}))
    return sim, rec, truth


def test_the_command_writes_a_readable_evaluation_of_every_bubble(static2d, capsys):
    sim, rec, truth = static2d
    assert main(["evaluate", str(rec), str(sim)]) == 0
    out = capsys.readouterr().out
    assert "{'" not in out and "DDI" in out and "1 missed" in out and "1 spurious" in out
    res = json.loads((rec / "evaluation.json").read_text())
    png = (rec / "evaluation.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10000
    # the output policy: both files are in the folder's manifest, so --overwrite removes them with the rest
    manifest = json.loads((rec / MANIFEST).read_text())
    assert {"evaluation.json", "evaluation.png", "bubbles.json"} <= set(manifest["files"])
    assert rec / "evaluation.json" in earlier_outputs(rec)
    assert res["field_of_view"] == {"radius_mm": 20.0, "half_height_mm": None}
    assert res["reconstruction"] == {"final_objective": 1.5, "iterations": 7, "stop_reason": "converged",
                                     "holdout_mse": 1e-4}
    by_truth = {m["truth_id"]: m for m in res["matches"]}
    assert len(by_truth) == len(truth)
    shrunk = by_truth[0]
    assert shrunk["reconstructed_id"] == 100 and shrunk["status"] == "found"
    assert shrunk["iou"] == pytest.approx(SHRINK ** 2, abs=0.02)
    area = truth[0].area
    assert shrunk["truth_area_mm2"] == pytest.approx(area, rel=0.02)
    assert shrunk["area_error_mm2"] == pytest.approx((SHRINK ** 2 - 1) * area, abs=0.02 * area)
    d = 2 * np.sqrt(area / np.pi)
    assert shrunk["equivalent_diameter_error_mm"] == pytest.approx((SHRINK - 1) * d, abs=0.01 * d)
    assert by_truth[1]["status"] == "missed" and by_truth[1]["reconstructed_id"] is None
    for k in range(2, len(truth)):
        assert by_truth[k]["reconstructed_id"] == 100 + k and by_truth[k]["iou"] > 0.97
    assert res["spurious_ids"] == [999]
    m = res["matching"]
    assert (m["found"], m["missed"], m["merged"], m["spurious"]) == (len(truth) - 1, 1, 0, 1)
    # the DDI from the areas: the shrunk bubble inside its truth, the dropped one missed, the disc extra
    areas = np.array([t.area for t in truth])
    both = areas[2:].sum() + SHRINK ** 2 * areas[0]
    rec_area = both + np.pi * 0.3 ** 2
    assert res["ddi"] == pytest.approx(1 - 2 * both / (rec_area + areas.sum()), abs=0.003)


def test_a_4d_folder_and_its_subscans_are_scored_per_subscan(tmp_path, capsys):
    sim = tmp_path / "sim4"
    assert main(["simulate", "--phantom", "expanding2d", "--subscans", "2", "--projections-per-subscan", "8",
                 "--det-count", "200", "--bubbles", "4", "--seed", "1", "--out", str(sim)]) == 0
    meta = json.loads((sim / "phantom.json").read_text())
    rec = tmp_path / "rec4"
    truths = []
    for k in range(2):
        truth, ids = read_polygons_json(sim / meta["truth"] / f"subscan_{k:04d}.json", with_ids=True)
        truths.append(truth)
        sub = rec / f"subscan_{k:04d}"
        sub.mkdir(parents=True)
        # subscan 1: bubble 0 shrunk; the track ids are the truth's
        write_polygons_json(sub / "bubbles.json", [_shrunk(truth[0])] + truth[1:] if k == 1 else truth, ids)
        (sub / "report.json").write_text(json.dumps({"dimension": 2}))
    assert main(["evaluate", str(rec), str(sim)]) == 0
    res = json.loads((rec / "evaluation.json").read_text())
    assert res["kind"] == "4d" and [p["subscan"] for p in res["subscans"]] == [0, 1]
    assert res["subscans"][0]["ddi"] == 0 and res["subscans"][0]["matching"]["found"] == len(truths[0])
    assert res["subscans"][1]["ddi"] > 0.002
    assert res["right_track_fraction"] == 1.0 and res["rows"] == len(truths[0]) + len(truths[1])
    assert (rec / "evaluation.png").is_file()
    out = capsys.readouterr().out
    assert "subscan   1: DDI" in out and "on the right track" in out
    # a subscan folder alone, against the 4D simulation's truth of that subscan
    one = evaluate_dir(rec / "subscan_0001", sim)
    assert one["kind"] == "subscan" and one["subscan"] == 1
    assert one["ddi"] == pytest.approx(res["subscans"][1]["ddi"], rel=1e-5)  # evaluation.json: 6 digits
    iou = {m["truth_id"]: m["iou"] for m in one["matches"]}
    assert iou[0] == pytest.approx(SHRINK ** 2, abs=0.03)


def test_3d_volumes_and_the_picture(tmp_path):
    sim, rec, truth = _simulated_and_altered(tmp_path, 3)
    res = evaluate_dir(rec, sim, True)
    shrunk = next(m for m in res["matches"] if m["truth_id"] == 0)
    assert shrunk["iou"] == pytest.approx(SHRINK ** 3, abs=0.03)
    v = truth[0].volume
    assert shrunk["volume_error_mm3"] == pytest.approx((SHRINK ** 3 - 1) * v, abs=0.03 * v)
    assert res["spurious_ids"] == [999] and res["field_of_view"] is None
    assert (rec / "evaluation.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.parametrize("case, words", [
    ("4d against static", "holds a static simulation"),
    ("static against 4d", "is no subscan_NNNN folder"),
    ("no bubbles", "run bubsub reconstruct (or reconstruct4d)"),
])
def test_mismatched_folders_are_refused_in_one_line(static2d, tmp_path, capsys, case, words):
    sim, rec, _ = static2d
    if case == "4d against static":
        shutil.copytree(rec, tmp_path / "r" / "subscan_0000")
        args = [tmp_path / "r", sim]
    elif case == "static against 4d":
        sim4 = tmp_path / "s4"
        sim4.mkdir()
        (sim4 / "phantom.json").write_text(json.dumps({"ndim": 2, "subscans": 2, "truth": "truth"}))
        args = [rec, sim4]
    else:
        args = [sim, sim]
    assert main(["evaluate", *map(str, args)]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1
