"""Mesh/polygon/table outputs: round trips, third-party readers (trimesh, plyfile), bad input, atomicity."""

import csv
import json
import os

import numpy as np
import pytest
import trimesh

from bubsub.core.projection.mesh import Polygon
from plyfile import PlyData, PlyElement

from bubsub.core.io import meshio, tables
from bubsub.core.io.meshio import read_ply, read_polygons_json, write_ply, write_polygons_json
from bubsub.core.io.tables import BUBBLE_COLUMNS_2D, BUBBLE_COLUMNS_3D, write_csv
from bubsub.core.analysis import shape
from bubsub.core.analysis.shape import bubble_table
from bubsub.core.foam.containers import sphere_mesh
from bubsub.core.foam.phantoms import foam2d
from bubsub.core.projection.subdivision import circle_surface, sphere_surface


@pytest.fixture(scope="module")
def bubbles3d():
    rng = np.random.default_rng(0)
    return [sphere_mesh(rng.uniform(-5, 5, 3), rng.uniform(0.5, 1.0), -0.1 - 0.01 * i) for i in range(4)]


# -- PLY -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_ply_round_trip(tmp_path, bubbles3d, binary):
    path = write_ply(tmp_path / "b.ply", bubbles3d, ids=[7, 3, 11, 5], binary=binary)
    meshes, ids = read_ply(path, with_ids=True)
    assert ids == [3, 5, 7, 11]  # ascending bubble_id
    by_id = dict(zip([7, 3, 11, 5], bubbles3d))
    for m, i in zip(meshes, ids):
        ref = by_id[i]
        assert np.array_equal(m.vertices, ref.vertices)  # doubles, written exactly
        assert np.array_equal(np.asarray(m.faces), np.asarray(ref.faces))
        assert m.attenuation == ref.attenuation
    assert os.listdir(tmp_path) == ["b.ply"]


def test_ply_is_readable_by_trimesh_with_bubble_ids(tmp_path, bubbles3d):
    path = write_ply(tmp_path / "b.ply", bubbles3d)
    tm = trimesh.load(path, process=False)
    assert tm.vertices.shape == (4 * 162, 3) and tm.faces.shape == (4 * 320, 3)
    assert tm.volume == pytest.approx(sum(m.volume for m in bubbles3d))
    face = tm.metadata["_ply_raw"]["face"]["data"]
    assert np.array_equal(np.unique(face["bubble_id"]), [0, 1, 2, 3])


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_ply_per_face_bubble_ids_read_back_by_plyfile_row_by_row(tmp_path, bubbles3d, binary):
    # plyfile's generic reader (no fixed list length: every face parsed on its own) as the independent reader
    path = write_ply(tmp_path / "b.ply", bubbles3d, ids=[7, 3, 11, 5], binary=binary)
    ply = PlyData.read(path)
    face, vertex = ply["face"].data, ply["vertex"].data
    assert [p.name for p in ply["face"].properties] == ["vertex_indices", "bubble_id", "attenuation"]
    assert np.array_equal(face["bubble_id"], np.repeat([7, 3, 11, 5], [len(m.faces) for m in bubbles3d]))
    assert np.array_equal(face["attenuation"], np.repeat([m.attenuation for m in bubbles3d], 320))
    offsets = np.cumsum([0] + [len(m.vertices) for m in bubbles3d[:-1]])
    want = np.concatenate([np.asarray(m.faces) + o for m, o in zip(bubbles3d, offsets)])
    assert np.array_equal(np.stack(face["vertex_indices"]), want)
    assert np.array_equal(np.c_[vertex["x"], vertex["y"], vertex["z"]], np.concatenate([m.vertices for m in bubbles3d]))


def test_ply_written_by_another_tool_big_endian_float_with_extra_elements(tmp_path, bubbles3d):
    m = bubbles3d[0]
    vertex = np.zeros(len(m.vertices), [("x", ">f4"), ("y", ">f4"), ("z", ">f4"), ("quality", ">f4")])
    vertex["x"], vertex["y"], vertex["z"] = m.vertices.T
    # (plyfile writes the scalars of a big-endian element with lists in native order: no bubble_id here)
    face = np.zeros(len(m.faces), [("vertex_indices", ">u4", (3,))])
    face["vertex_indices"] = m.faces
    camera = np.zeros(1, [("view_px", ">f4")])
    path = tmp_path / "other.ply"
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face"),
             PlyElement.describe(camera, "camera")], byte_order=">").write(path)
    (back,), ids = read_ply(path, attenuation=-0.1, with_ids=True)
    assert ids == [0]  # one connected component
    assert np.array_equal(back.vertices, m.vertices.astype(np.float32).astype(np.float64))
    assert np.array_equal(np.asarray(back.faces), np.asarray(m.faces))


def test_the_tables_have_one_home():
    # meshio reads and writes meshes; the CSV tables live in tables.py only; the bubble table's rows are measured
    # by the analysis (its definitions of volume and area), which writes through tables.py
    for name in ("write_csv", "csv_metadata_path", "unit_column", "BUBBLE_COLUMN_INFO"):
        assert hasattr(tables, name) and not hasattr(meshio, name)
    assert hasattr(shape, "bubble_table") and not hasattr(tables, "bubble_table") and not hasattr(meshio, "bubble_table")


def test_ply_without_bubble_ids_is_split_into_components(tmp_path, bubbles3d):
    tm = trimesh.util.concatenate([trimesh.Trimesh(m.vertices, m.faces, process=False) for m in bubbles3d])
    path = tmp_path / "plain.ply"
    tm.export(path)
    with pytest.raises(ValueError, match="no 'attenuation' property; pass attenuation="):
        read_ply(path)
    meshes = read_ply(path, attenuation=-0.1)
    assert len(meshes) == 4
    assert [m.volume for m in meshes] == pytest.approx([m.volume for m in bubbles3d])
    assert all(m.attenuation == -0.1 for m in meshes)


def test_ply_attenuation_override(tmp_path, bubbles3d):
    path = write_ply(tmp_path / "b.ply", bubbles3d[:2])
    assert [m.attenuation for m in read_ply(path, attenuation=-0.2)] == [-0.2, -0.2]


def test_ply_accepts_subdivision_surfaces(tmp_path):
    s = sphere_surface((0, 0, 0), 1.0, -0.1)
    meshes = read_ply(write_ply(tmp_path / "s.ply", [s]))
    assert len(meshes[0].vertices) == len(s.fine().vertices)


def test_ply_bad_input(tmp_path, bubbles3d):
    junk = tmp_path / "junk.ply"
    junk.write_text("solid nothing\n")
    with pytest.raises(ValueError, match="not a PLY file"):
        read_ply(junk)
    quad = tmp_path / "quad.ply"
    quad.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
    )
    with pytest.raises(ValueError, match="only triangle faces"):
        read_ply(quad, attenuation=1.0)
    quad_bin = tmp_path / "quad_bin.ply"  # the binary reader expects lists of three
    vertex = np.zeros(4, [("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    PlyData([PlyElement.describe(vertex, "vertex"),
             PlyElement.describe(np.array([([0, 1, 2, 3],)], [("vertex_indices", "<i4", (4,))]), "face")]).write(quad_bin)
    with pytest.raises(ValueError, match="only triangle faces"):
        read_ply(quad_bin, attenuation=1.0)
    # an open bubble (one face removed) is reported with its id
    m = bubbles3d[0]
    tm = trimesh.Trimesh(m.vertices, np.asarray(m.faces)[1:], process=False)
    openp = tmp_path / "open.ply"
    tm.export(openp)
    with pytest.raises(ValueError, match="bubble 0: mesh is not closed"):
        read_ply(openp, attenuation=-0.1)
    with pytest.raises(ValueError, match="ids has 1 entries but there are 4"):
        write_ply(tmp_path / "x.ply", bubbles3d, ids=[1])
    with pytest.raises(ValueError, match=r"meshes\[0\] is a Polygon"):
        write_ply(tmp_path / "x.ply", [Polygon([[0, 0], [1, 0], [0, 1]])])
    with pytest.raises(ValueError, match="does not exist"):
        write_ply(tmp_path / "no" / "x.ply", bubbles3d)
    assert not (tmp_path / "x.ply").exists()


def test_truncated_binary_ply_is_rejected(tmp_path, bubbles3d):
    path = write_ply(tmp_path / "b.ply", bubbles3d)
    raw = path.read_bytes()
    path.write_bytes(raw[:-100])
    with pytest.raises(ValueError, match="truncated"):
        read_ply(path)


# -- JSON ---------------------------------------------------------------------------------------------
def test_polygons_json_round_trip_and_format(tmp_path):
    ph = foam2d(0, n_bubbles=6)
    path = write_polygons_json(tmp_path / "p.json", ph.bubbles, ids=range(10, 16))
    doc = json.loads(path.read_text())
    assert [b["id"] for b in doc["bubbles"]] == list(range(10, 16))
    assert len(doc["bubbles"][0]["vertices"]) == 128 and len(doc["bubbles"][0]["vertices"][0]) == 2
    polys, ids = read_polygons_json(path, with_ids=True)
    assert ids == list(range(10, 16))
    for p, q in zip(polys, ph.bubbles):
        assert np.array_equal(p.vertices, q.vertices) and p.attenuation == q.attenuation
    assert read_polygons_json(path, attenuation=-0.3)[0].attenuation == -0.3
    circ = circle_surface((0, 0), 1.0, -0.1)
    assert len(read_polygons_json(write_polygons_json(tmp_path / "c.json", [circ]))[0].vertices) == len(
        circ.fine().vertices)


def test_polygons_json_accepts_a_repeated_closing_vertex(tmp_path):
    (tmp_path / "p.json").write_text(json.dumps(
        {"bubbles": [{"id": 1, "attenuation": -0.1, "vertices": [[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]]}]}))
    (poly,) = read_polygons_json(tmp_path / "p.json")
    assert len(poly.vertices) == 4 and poly.area == pytest.approx(1.0)


@pytest.mark.parametrize(
    "doc, word",
    [
        ("not json", "invalid JSON"),
        ({"polygons": []}, "'bubbles' list"),
        ({"bubbles": [{"vertices": [[0, 0], [1, 0], [0, 1]]}]}, "no integer 'id'"),
        ({"bubbles": [{"id": 2, "attenuation": 1, "vertices": [[0, 0], [0, 1], [1, 0]]}]}, "bubble 2: vertices are clockwise"),
        ({"bubbles": [{"id": 2, "attenuation": 1, "vertices": [[0, 0], [1, 0]]}]}, "at least 3 vertices"),
        ({"bubbles": [{"id": 2, "attenuation": 1, "vertices": [[0, 0], [1, "a"], [0, 1]]}]}, "list of \\[x, y\\]"),
        ({"bubbles": [{"id": 2, "vertices": [[0, 0], [1, 0], [0, 1]]}]}, "no 'attenuation'"),
        ({"bubbles": [{"id": 1, "attenuation": 1, "vertices": [[0, 0], [1, 0], [0, 1]]},
                      {"id": 1, "attenuation": 1, "vertices": [[0, 0], [1, 0], [0, 1]]}]}, "duplicate bubble id 1"),
    ],
)
def test_polygons_json_bad_input(tmp_path, doc, word):
    path = tmp_path / "p.json"
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    with pytest.raises(ValueError, match=word):
        read_polygons_json(path)


# -- tables ---------------------------------------------------------------------------------------------
def test_bubble_table_2d_against_circle_formulas():
    t = 2 * np.pi * np.arange(2048) / 2048
    r = 0.7
    poly = Polygon(np.c_[1.0 + r * np.cos(t), -2.0 + r * np.sin(t)], -0.1)
    (row,) = bubble_table([poly], ids=[4])
    assert tuple(row) == BUBBLE_COLUMNS_2D
    assert row["id"] == 4
    assert row["centroid_x_mm"] == pytest.approx(1.0) and row["centroid_y_mm"] == pytest.approx(-2.0)
    assert row["area_mm2"] == pytest.approx(np.pi * r * r, rel=1e-5)
    assert row["perimeter_mm"] == pytest.approx(2 * np.pi * r, rel=1e-5)
    assert row["equivalent_diameter_mm"] == pytest.approx(2 * r, rel=1e-5)


def test_bubble_table_3d_against_sphere_formulas():
    m = sphere_mesh((1.0, 2.0, -3.0), 0.8, -0.1, subdivisions=4)
    (row,) = bubble_table(m)
    assert tuple(row) == BUBBLE_COLUMNS_3D
    assert [row["centroid_x_mm"], row["centroid_y_mm"], row["centroid_z_mm"]] == pytest.approx([1.0, 2.0, -3.0])
    assert row["volume_mm3"] == pytest.approx(4 / 3 * np.pi * 0.8**3, rel=3e-3)
    assert row["surface_area_mm2"] == pytest.approx(4 * np.pi * 0.8**2, rel=3e-3)
    assert row["equivalent_diameter_mm"] == pytest.approx(1.6, rel=1e-3)


def test_bubble_table_rejects_mixed_items(bubbles3d):
    with pytest.raises(ValueError, match="all Mesh or all Polygon"):
        bubble_table([bubbles3d[0], Polygon([[0, 0], [1, 0], [0, 1]])])
    assert bubble_table([]) == []


def test_csv_round_trip(tmp_path, bubbles3d):
    rows = bubble_table(bubbles3d, ids=[9, 8, 7, 6])
    path = write_csv(tmp_path / "t.csv", rows)
    with open(path, newline="") as fh:
        back = list(csv.DictReader(fh))
    assert list(back[0]) == list(BUBBLE_COLUMNS_3D)
    assert [int(r["id"]) for r in back] == [9, 8, 7, 6]
    # six significant digits (bubsub.core.io.tables.SIGNIFICANT_DIGITS)
    assert [float(r["volume_mm3"]) for r in back] == pytest.approx([r["volume_mm3"] for r in rows], rel=5e-6)
    assert all(len(r["volume_mm3"].replace(".", "").lstrip("0")) <= 6 for r in back)


def test_csv_bad_rows_and_failed_write(tmp_path):
    with pytest.raises(ValueError, match=r"rows\[1\] keys differ .*missing \['b'\]"):
        write_csv(tmp_path / "t.csv", [{"a": 1, "b": 2}, {"a": 3}])
    assert not (tmp_path / "t.csv").exists()
    write_csv(tmp_path / "t.csv", [{"a": 1}])
    before = (tmp_path / "t.csv").read_text()

    class Explodes:
        def __str__(self):
            raise RuntimeError("cannot format")

    with pytest.raises(RuntimeError, match="cannot format"):
        write_csv(tmp_path / "t.csv", [{"a": 1}, {"a": Explodes()}])
    assert (tmp_path / "t.csv").read_text() == before
    assert os.listdir(tmp_path) == ["t.csv"]
    assert write_csv(tmp_path / "e.csv", []).read_text() == ""
    assert write_csv(tmp_path / "h.csv", [], columns=BUBBLE_COLUMNS_2D).read_text().strip() == ",".join(
        BUBBLE_COLUMNS_2D)



def test_column_names_carry_their_units_and_the_sidecar_describes_them(tmp_path, bubbles3d):
    from bubsub.core.io.tables import BUBBLE_COLUMN_INFO, csv_metadata_path, unit_column

    assert unit_column("volume", "mm^3") == "volume_mm3" and unit_column("id", "") == "id"
    assert unit_column("attenuation", "1/mm") == "attenuation_per_mm"
    with pytest.raises(ValueError, match="unknown unit"):
        unit_column("x", "furlong")
    # every measured column ends with the unit its description gives
    for name, (unit, _) in BUBBLE_COLUMN_INFO.items():
        assert name == "id" or name.endswith("_" + unit.replace("^", ""))
    path = write_csv(tmp_path / "b.csv", bubble_table(bubbles3d), describe=BUBBLE_COLUMN_INFO, title="bubbles")
    meta = json.loads(csv_metadata_path(path).read_text())
    assert csv_metadata_path(path).name == "b.csv-metadata.json" and meta["url"] == "b.csv"
    assert [c["name"] for c in meta["tableSchema"]["columns"]] == list(BUBBLE_COLUMNS_3D)
    assert meta["tableSchema"]["columns"][4]["unit"] == "mm^3"
    # an undescribed column writes neither file
    with pytest.raises(ValueError, match="'extra' has no"):
        write_csv(tmp_path / "c.csv", [{"extra": 1}], describe=BUBBLE_COLUMN_INFO)
    assert not (tmp_path / "c.csv").exists() and not csv_metadata_path(tmp_path / "c.csv").exists()
