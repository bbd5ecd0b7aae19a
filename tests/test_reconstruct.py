"""End to end: bubsub simulate -> reconstruct -> evaluate, through the CLI."""

import csv
import json

import h5py
import numpy as np
import pytest

from bubsub.clients.cli import main
from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir
from bubsub.core import MeshProjector
from bubsub.core.io.meshio import read_polygons_json


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    rc = main(["simulate", "--phantom", "foam2d", "--bubbles", "12", "--det-count", "400", "--angles", "30",
               "--photons", "1e4", "--seed", "3", "--out", str(out)])
    assert rc == 0
    return out


@pytest.fixture(scope="module")
def rec(sim, tmp_path_factory):
    out = tmp_path_factory.mktemp("rec")
    rc = main(["reconstruct", str(sim / "scan.h5"), "--out", str(out), "--holdout", "odd", "--iterations", "60", "--quiet"])
    assert rc == 0
    return out


def test_simulation_folder(sim):
    meta = json.loads((sim / "phantom.json").read_text())
    assert meta["bubbles"] == 12 and meta["seed"] == 3
    with h5py.File(sim / "scan.h5") as f:
        assert f["exchange/data"].shape == (30, 400)
        assert f["exchange/data"].dtype == np.float32
        assert f["geometry/vectors"].attrs["kind"] == "parallel_vec"
    assert len(read_polygons_json(sim / "truth.json")) == 12


def test_reconstruction_matches_the_truth(sim, rec, capsys):
    report = json.loads((rec / "report.json").read_text())
    assert report["bubbles"] == 12
    assert report["projections_used"] == 15 and report["holdout_projections"] == 15
    assert report["final_objective"] < report["initial_objective"]
    assert report["holdout_mse"] < 1e-3
    # the paper's voxel reference (30 BB iterations) on the same held-out projections does worse than the meshes
    assert report["holdout_mse"] < report["holdout_mse_voxel_bb"]
    parts, cpu = report["seconds_parts"], report["cpu_seconds_parts"]
    assert list(parts) == ["preview", "initial_bubbles", "radius_estimation", "fit", "topology", "validity", "refine",
                           "holdout"]
    # the coarse-to-fine step ran and the written control outlines are the ones its decision kept
    ref = report["refinement"]
    assert (ref["control_vertices_before"], ref["control_vertices_after"]) == (9, 18)
    assert ref["kept"] == (ref["score_after"] < ref["score_before"] and ref.get("score_after_repair", -np.inf)
                           < ref["score_before"])
    sizes = {len(p.vertices) for p in read_polygons_json(rec / "control.json")}
    assert sizes == ({18} if ref["kept"] else {9})
    assert set(cpu) == set(parts) and min(parts.values()) >= 0 and min(cpu.values()) >= 0
    assert sum(parts.values()) - parts["holdout"] <= report["seconds_total"] + 1e-6 and parts["fit"] > 0
    res = evaluate_dir(rec, sim)
    assert res["ddi"] < 0.03
    assert main(["evaluate", str(rec), str(sim)]) == 0
    out = capsys.readouterr().out
    assert "DDI (lower is better)" in out and "0 is a perfect match" in out


def test_outputs_are_readable(rec):
    polys = read_polygons_json(rec / "bubbles.json")
    assert all(p.area > 0 for p in polys)
    with open(rec / "bubbles.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(polys)
    for r, p in zip(rows, polys):
        assert float(r["area_mm2"]) == pytest.approx(p.area, rel=5e-6)  # six significant digits
    meta = json.loads((rec / "bubbles.csv-metadata.json").read_text())
    described = [c["name"] for c in meta["tableSchema"]["columns"]]
    assert described == list(rows[0]) and meta["url"] == "bubbles.csv"
    assert {c["name"]: c.get("unit") for c in meta["tableSchema"]["columns"]}["area_mm2"] == "mm^2"
    assert (rec / "overlay.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(read_polygons_json(rec / "control.json")) == len(polys)


def test_previous_reconstruction_as_initial_mesh(sim, rec, tmp_path):
    out = tmp_path / "again"
    rc = main(["reconstruct", str(sim / "scan.h5"), "--out", str(out), "--init", str(rec / "control.json"),
               "--iterations", "5", "--quiet"])
    assert rc == 0
    assert evaluate_dir(out, sim)["ddi"] < 0.03
    assert json.loads((out / "report.json").read_text())["bubbles_initial"] == 12


def test_ctrl_c_leaves_a_usable_partial_result(sim, tmp_path, monkeypatch):
    calls = {"n": 0}
    original = MeshProjector.objective

    def interrupted(self, meshes, data):
        calls["n"] += 1
        if calls["n"] > 12:
            raise KeyboardInterrupt
        return original(self, meshes, data)

    monkeypatch.setattr(MeshProjector, "objective", interrupted)
    out = tmp_path / "partial"
    rc = main(["reconstruct", str(sim / "scan.h5"), "--out", str(out), "--quiet", "--no-radius-estimation"])
    assert rc == 130
    report = json.loads((out / "report.json").read_text())
    assert report["interrupted"] is True and report["bubbles"] > 0
    assert len(read_polygons_json(out / "bubbles.json")) == report["bubbles"]


def test_broken_scan_files_give_a_clear_error_and_no_output(sim, tmp_path, capsys):
    bad = tmp_path / "bad.h5"
    with h5py.File(sim / "scan.h5") as src, h5py.File(bad, "w") as dst:
        for k, v in src.attrs.items():
            dst.attrs[k] = v
        src.copy("geometry", dst)
    out = tmp_path / "out"
    assert main(["reconstruct", str(bad), "--out", str(out), "--quiet"]) == 2
    assert "exchange/data" in capsys.readouterr().err
    assert not out.exists()
    assert main(["reconstruct", str(tmp_path / "missing.h5"), "--out", str(out), "--quiet"]) == 2
    assert not out.exists()


def test_reconstruct_against_a_projector_server(sim, rec, tmp_path):
    from service_support import ServerThread

    out = tmp_path / "remote"
    with ServerThread() as server:
        rc = main(["reconstruct", str(sim / "scan.h5"), "--out", str(out), "--holdout", "odd", "--iterations", "60",
                   "--quiet", "--server", server.url])
        assert rc == 0
        assert len(server.state.store) == 0  # the CLI deleted its job
    local = json.loads((rec / "report.json").read_text())
    remote = json.loads((out / "report.json").read_text())
    # where the projections ran: the fit on the server, every other phase here
    assert remote["projector"]["server"] == server.url and remote["projector"]["remote_phases"] == ["fit"]
    assert set(remote["projector"]["local_phases"]) == set(remote["seconds_parts"]) - {"fit"}
    assert local["projector"]["server"] is None and local["projector"]["remote_phases"] == []
    assert "fit" in local["projector"]["local_phases"]
    assert remote["bubbles"] == local["bubbles"]
    assert remote["final_objective"] == pytest.approx(local["final_objective"], rel=1e-3)
    assert evaluate_dir(out, sim)["ddi"] < 0.03


def test_ctrl_c_in_the_topology_rounds_stops_them_and_writes_the_first_fit(sim, tmp_path, monkeypatch):
    from bubsub.clients.pipeline.static import topology

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(topology, "add_step", ctrl_c)
    out = tmp_path / "partial"
    rc = main(["reconstruct", str(sim / "scan.h5"), "--out", str(out), "--quiet", "--iterations", "5"])
    assert rc == 130
    report = json.loads((out / "report.json").read_text())
    assert report["interrupted"] is True and report["stop_reason"] == "interrupted"
    assert report["topology"] is None and report["validity"]["repaired"] is False
    assert len(read_polygons_json(out / "bubbles.json")) == report["bubbles"] > 0


def test_resample_image_reproduces_a_linear_field_between_grids():
    """Trilinear resampling (the coarse-to-fine 3D preview) is exact for a linear field inside the old grid;
    axes follow the grid convention (x columns, y rows downwards, z slices)."""
    from bubsub.clients.pipeline.static.preview import resample_image
    from bubsub.core.voxel.grid import index_to_world

    def field(shape, extent):
        xyz = index_to_world(np.indices(shape).reshape(3, -1).T, shape, extent)
        return (0.3 * xyz[:, 0] - 0.7 * xyz[:, 1] + 1.1 * xyz[:, 2] + 0.2).reshape(shape)

    old = ((10, 20, 24), (-1.2, 1.2, -1.0, 1.0, -0.5, 0.5))
    new = ((17, 33, 41), (-1.0, 1.1, -0.9, 0.8, -0.4, 0.45))  # inside the old grid's voxel centres
    out = resample_image(field(*old).astype(np.float32), old[1], *new)
    assert out.shape == new[0] and out.dtype == np.float32
    np.testing.assert_allclose(out, field(*new), atol=2e-5)
