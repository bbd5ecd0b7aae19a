"""Reconstruction outputs: bubble meshes (PLY), bubble polygons (JSON), bubble tables (CSV).

One module of about 630 lines on purpose: the three writers share the id and
attenuation bookkeeping (``_resolve``, ``_ids``) and their readers must round-trip
exactly what the writers emit, which the tests check pairwise.

Formats
-------
PLY (3D)
    All bubbles in one file (binary little-endian by default, or ASCII):
    ``vertex`` with ``double x, y, z`` (mm), ``face`` with
    ``list uchar int vertex_indices``, ``int bubble_id`` and
    ``double attenuation`` (1/mm). MeshLab, trimesh and other PLY readers
    open it; extra face properties are ignored by readers that do not
    know them. :func:`read_ply` groups the faces by ``bubble_id`` (or, in
    files without it, by connected component).
JSON (2D)
    ``{"units": "mm", "bubbles": [{"id": int, "attenuation": float,
    "vertices": [[x, y], ...]}, ...]}``, vertices counter-clockwise, the
    first vertex not repeated at the end.
CSV
    One row per bubble: ``id, centroid_x_mm, centroid_y_mm[, centroid_z_mm],
    area_mm2 | volume_mm3, perimeter_mm | surface_area_mm2,
    equivalent_diameter_mm``; see :func:`bubble_table`. Every column name
    ends with its unit (:func:`unit_column`), and :func:`write_csv` can write
    a sidecar ``NAME.csv-metadata.json`` (W3C CSV on the Web metadata)
    describing each column, its unit and type.

All writers are atomic (:mod:`bubsub.core.io.atomic`).
"""

from __future__ import annotations

import csv
import io
import json
import numbers
from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_open
from bubsub.core.projection.mesh import Mesh, Polygon

__all__ = [
    "write_ply",
    "read_ply",
    "write_polygons_json",
    "read_polygons_json",
    "bubble_table",
    "write_csv",
    "csv_metadata_path",
    "unit_column",
    "BUBBLE_COLUMNS_2D",
    "BUBBLE_COLUMNS_3D",
    "BUBBLE_COLUMN_INFO",
]

#: How a unit is written at the end of a column name (``volume`` in mm^3 is ``volume_mm3``).
UNIT_SUFFIXES = {"": "", "mm": "mm", "mm^2": "mm2", "mm^3": "mm3", "1/mm": "per_mm", "s": "s", "deg": "deg",
                 "subscan": "subscan", "1": ""}


def unit_column(quantity, unit):
    """A column name that carries its unit: ``unit_column("volume", "mm^3") == "volume_mm3"``.

    Parameters
    ----------
    quantity : str
        E.g. ``"centroid_x"``.
    unit : str
        One of :data:`UNIT_SUFFIXES` (``""`` or ``"1"`` for counts, ids and
        other dimensionless columns, which keep their bare name).

    Returns
    -------
    str
    """
    if unit not in UNIT_SUFFIXES:
        raise ValueError(f"unknown unit {unit!r}; known: {sorted(UNIT_SUFFIXES)}")
    suffix = UNIT_SUFFIXES[unit]
    return f"{quantity}_{suffix}" if suffix else quantity


#: ``column name: (unit, meaning)`` of every column :func:`bubble_table` writes.
BUBBLE_COLUMN_INFO = {
    "id": ("", "bubble id (the bubble_id of the PLY faces / the id of the JSON polygon)"),
    **{unit_column(f"centroid_{a}", "mm"): ("mm", f"{a} coordinate of the centroid of the refined surface")
       for a in "xyz"},
    unit_column("area", "mm^2"): ("mm^2", "area enclosed by the refined 2D outline"),
    unit_column("perimeter", "mm"): ("mm", "length of the refined 2D outline"),
    unit_column("volume", "mm^3"): ("mm^3", "volume enclosed by the refined 3D surface"),
    unit_column("surface_area", "mm^2"): ("mm^2", "area of the refined 3D surface"),
    unit_column("equivalent_diameter", "mm"): (
        "mm", "diameter of the disc (2D) or ball (3D) of the same area (volume)"),
}

#: Columns of :func:`bubble_table` for 2D bubbles.
BUBBLE_COLUMNS_2D = ("id", "centroid_x_mm", "centroid_y_mm", "area_mm2", "perimeter_mm", "equivalent_diameter_mm")
#: Columns of :func:`bubble_table` for 3D bubbles.
BUBBLE_COLUMNS_3D = ("id", "centroid_x_mm", "centroid_y_mm", "centroid_z_mm", "volume_mm3", "surface_area_mm2",
                     "equivalent_diameter_mm")


# -- common --------------------------------------------------------------------------
def _resolve(items, want, what):
    """Items as a list of ``want`` (Mesh or Polygon); SubdivisionSurfaces are refined."""
    if isinstance(items, (Mesh, Polygon)) or hasattr(items, "fine"):
        items = [items]
    try:
        items = list(items)
    except TypeError:
        raise ValueError(f"{what} must be a sequence of {want.__name__}, got {type(items).__name__}") from None
    out = []
    for i, it in enumerate(items):
        if not isinstance(it, (Mesh, Polygon)) and hasattr(it, "fine"):
            it = it.fine()
        if not isinstance(it, want):
            raise ValueError(f"{what}[{i}] is a {type(it).__name__}, expected a {want.__name__}")
        out.append(it)
    return out


def _ids(ids, n):
    if ids is None:
        return list(range(n))
    try:
        ids = list(ids)
    except TypeError:
        raise ValueError(f"ids must be a sequence of integers, got {type(ids).__name__}") from None
    if len(ids) != n:
        raise ValueError(f"ids has {len(ids)} entries but there are {n} bubbles")
    out = []
    for i in ids:
        if isinstance(i, bool) or not isinstance(i, numbers.Integral):
            raise ValueError(f"ids must be integers, got {i!r}")
        out.append(int(i))
    if len(set(out)) != len(out):
        raise ValueError("ids must be unique")
    return out


# -- PLY ---------------------------------------------------------------------------------
def write_ply(path, meshes, ids=None, *, binary=True):
    """Write bubble meshes to one PLY file with a per-face ``bubble_id``.

    Parameters
    ----------
    path : str or os.PathLike
    meshes : sequence of Mesh (or SubdivisionSurface, written refined)
    ids : sequence of int, optional
        Bubble ids (default ``0..n-1``); must fit in int32.
    binary : bool
        Binary little-endian (default) or ASCII.

    Returns
    -------
    pathlib.Path
    """
    ms = _resolve(meshes, Mesh, "meshes")
    bid = _ids(ids, len(ms))
    if any(not -(2**31) <= i < 2**31 for i in bid):
        raise ValueError("ids must fit in a 32-bit signed integer")
    n_v = sum(len(m.vertices) for m in ms)
    n_f = sum(len(m.faces) for m in ms)
    if n_v >= 2**31:
        raise ValueError("too many vertices for a PLY file with int indices")
    verts = np.concatenate([m.vertices for m in ms]) if ms else np.zeros((0, 3))
    offsets = np.cumsum([0] + [len(m.vertices) for m in ms])
    faces = np.concatenate([np.asarray(m.faces) + o for m, o in zip(ms, offsets[:-1])]) if ms else np.zeros((0, 3), int)
    face_id = np.repeat(np.array(bid, dtype=np.int64), [len(m.faces) for m in ms]) if ms else np.zeros(0, int)
    face_mu = np.repeat(np.array([m.attenuation for m in ms]), [len(m.faces) for m in ms]) if ms else np.zeros(0)
    header = (
        "ply\n"
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0\n"
        "comment bubsub bubble meshes; units mm, attenuation 1/mm\n"
        f"element vertex {n_v}\n"
        "property double x\nproperty double y\nproperty double z\n"
        f"element face {n_f}\n"
        "property list uchar int vertex_indices\n"
        "property int bubble_id\n"
        "property double attenuation\n"
        "end_header\n"
    )
    with atomic_open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        if binary:
            fh.write(np.ascontiguousarray(verts, dtype="<f8").tobytes())
            rec = np.zeros(n_f, dtype=[("n", "u1"), ("v", "<i4", (3,)), ("id", "<i4"), ("mu", "<f8")])
            rec["n"] = 3
            rec["v"] = faces
            rec["id"] = face_id
            rec["mu"] = face_mu
            fh.write(rec.tobytes())
        else:
            buf = io.StringIO()
            for x, y, z in verts.tolist():
                buf.write(f"{x!r} {y!r} {z!r}\n")
            for (a, b, c), i, mu in zip(faces.tolist(), face_id.tolist(), face_mu.tolist()):
                buf.write(f"3 {a} {b} {c} {i} {mu!r}\n")
            fh.write(buf.getvalue().encode("ascii"))
    return Path(path)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _parse_header(raw, name):
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise ValueError(f"{name} is not a PLY file (no 'ply' magic or no 'end_header')")
    nl = raw.find(b"\n", end)
    if nl < 0:
        raise ValueError(f"{name}: truncated PLY header")
    lines = raw[:nl].decode("ascii", errors="replace").replace("\r", "").split("\n")
    fmt, elements = None, []
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info", "end_header"):
            continue
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise ValueError(f"{name}: unsupported PLY format line {line!r}")
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise ValueError(f"{name}: bad PLY element line {line!r}")
            elements.append({"name": tok[1], "count": int(tok[2]), "props": []})
        elif tok[0] == "property":
            if not elements:
                raise ValueError(f"{name}: PLY property before any element")
            if len(tok) == 5 and tok[1] == "list":
                if tok[2] not in _PLY_TYPES or tok[3] not in _PLY_TYPES:
                    raise ValueError(f"{name}: unknown PLY type in {line!r}")
                elements[-1]["props"].append((tok[4], "list", tok[2], tok[3]))
            elif len(tok) == 3 and tok[1] in _PLY_TYPES:
                elements[-1]["props"].append((tok[2], "scalar", tok[1], None))
            else:
                raise ValueError(f"{name}: bad PLY property line {line!r}")
        else:
            raise ValueError(f"{name}: unexpected PLY header line {line!r}")
    if fmt is None:
        raise ValueError(f"{name}: PLY header has no format line")
    return fmt, elements, nl + 1


def _read_elements(raw, fmt, elements, start, name):
    """Parse vertex and face elements: {element name: {property: array}}."""
    out = {}
    if fmt == "ascii":
        text = raw[start:].decode("ascii", errors="replace").split("\n")
        lines = [ln for ln in (t.strip() for t in text) if ln]
        pos = 0
        for el in elements:
            rows = lines[pos: pos + el["count"]]
            if len(rows) < el["count"]:
                raise ValueError(f"{name}: PLY element '{el['name']}' has {len(rows)} of {el['count']} lines")
            pos += el["count"]
            out[el["name"]] = _ascii_element(rows, el, name)
        return out
    order = "<" if fmt == "binary_little_endian" else ">"
    offset = start
    for el in elements:
        fields = []
        for pname, kind, t1, t2 in el["props"]:
            if kind == "scalar":
                fields.append((pname, order + _PLY_TYPES[t1]))
            else:  # lists are read as triangles, then checked
                fields.append((pname + "__n", order + _PLY_TYPES[t1]))
                fields.append((pname, order + _PLY_TYPES[t2], (3,)))
        dt = np.dtype(fields)
        nbytes = dt.itemsize * el["count"]
        if offset + nbytes > len(raw):
            raise ValueError(f"{name}: PLY file is truncated in element '{el['name']}'")
        rec = np.frombuffer(raw, dtype=dt, count=el["count"], offset=offset)
        for pname, kind, _, _ in el["props"]:
            if kind == "list" and el["count"] and np.any(rec[pname + "__n"] != 3):
                if el["name"] == "face":
                    raise ValueError(f"{name}: only triangle faces are supported")
                return out  # an unknown element with lists: stop, vertex/face are read already
        out[el["name"]] = {p[0]: np.array(rec[p[0]]) for p in el["props"]}
        offset += nbytes
    return out


def _ascii_element(rows, el, name):
    props = el["props"]
    lists = [p for p in props if p[1] == "list"]
    try:
        tok = np.array([r.split() for r in rows], dtype=float) if rows else np.zeros((0, 0))
    except ValueError:
        if lists and el["name"] == "face":
            raise ValueError(f"{name}: only triangle faces are supported") from None
        raise ValueError(f"{name}: malformed ASCII PLY element '{el['name']}'") from None
    res, col = {}, 0
    for pname, kind, _, _ in props:
        if kind == "scalar":
            res[pname] = tok[:, col] if len(rows) else np.zeros(0)
            col += 1
        else:
            if len(rows) and np.any(tok[:, col] != 3):
                raise ValueError(f"{name}: only triangle faces are supported")
            res[pname] = tok[:, col + 1: col + 4].astype(np.int64) if len(rows) else np.zeros((0, 3), int)
            col += 4
    if len(rows) and tok.shape[1] != col:
        raise ValueError(f"{name}: ASCII PLY element '{el['name']}' has {tok.shape[1]} values per line, expected {col}")
    return res


def read_ply(path, attenuation=None, *, with_ids=False):
    """Read bubble meshes from a PLY file, one Mesh per ``bubble_id``.

    Parameters
    ----------
    path : str or os.PathLike
    attenuation : float, optional
        Attenuation of every bubble (1/mm); overrides the file's per-face
        ``attenuation``. Required if the file has none.
    with_ids : bool
        Also return the bubble ids.

    Returns
    -------
    meshes : list of Mesh
        Ordered by ascending ``bubble_id``; vertices renumbered per bubble.
        Files without ``bubble_id`` are split into connected components
        (ids 0, 1, ... in order of first appearance).
    ids : list of int
        Only with ``with_ids=True``.

    Raises
    ------
    ValueError
        If the file is not a (triangle) PLY, lacks vertex/face elements,
        indices are out of range, a bubble is not a closed outward mesh, a
        bubble's faces disagree on attenuation, or no attenuation is known.
    """
    p = Path(path)
    raw = p.read_bytes()
    fmt, elements, start = _parse_header(raw, p.name)
    names = [e["name"] for e in elements]
    for need in ("vertex", "face"):
        if need not in names:
            raise ValueError(f"{p.name}: PLY file has no '{need}' element")
    data = _read_elements(raw, fmt, elements, start, p.name)
    if "vertex" not in data or "face" not in data:
        raise ValueError(f"{p.name}: could not read the vertex and face elements")
    vx = data["vertex"]
    if not all(k in vx for k in "xyz"):
        raise ValueError(f"{p.name}: PLY vertices need properties x, y and z")
    verts = np.stack([vx["x"], vx["y"], vx["z"]], axis=1).astype(np.float64)
    fc = data["face"]
    key = "vertex_indices" if "vertex_indices" in fc else ("vertex_index" if "vertex_index" in fc else None)
    if key is None:
        raise ValueError(f"{p.name}: PLY faces need a list property 'vertex_indices'")
    faces = np.asarray(fc[key], dtype=np.int64).reshape(-1, 3)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(verts)):
        raise ValueError(f"{p.name}: face indices out of range [0, {len(verts)})")
    if "bubble_id" in fc:
        fid = np.asarray(fc["bubble_id"]).astype(np.int64)
    else:
        fid = _components(faces, len(verts))
    mu_face = np.asarray(fc["attenuation"], dtype=np.float64) if "attenuation" in fc else None
    if attenuation is None and mu_face is None:
        raise ValueError(f"{p.name}: faces have no 'attenuation' property; pass attenuation=")
    meshes, ids = [], []
    for i in np.unique(fid):
        sel = fid == i
        f = faces[sel]
        used, inv = np.unique(f, return_inverse=True)
        if attenuation is not None:
            mu = attenuation
        else:
            vals = mu_face[sel]
            if np.any(vals != vals[0]):
                raise ValueError(f"{p.name}: bubble {int(i)} has faces with different attenuations")
            mu = float(vals[0])
        try:
            meshes.append(Mesh(verts[used], inv.reshape(-1, 3), mu))
        except ValueError as exc:
            raise ValueError(f"{p.name}: bubble {int(i)}: {exc}") from None
        ids.append(int(i))
    return (meshes, ids) if with_ids else meshes


def _components(faces, n_vertices):
    """Connected-component id of each face, numbered in order of first appearance."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    if len(faces) == 0:
        return np.zeros(0, dtype=np.int64)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    g = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    _, lab = connected_components(g, directed=False)
    comp = lab[faces[:, 0]]
    _, first = np.unique(comp, return_index=True)
    rank = np.empty(comp.max() + 1, dtype=np.int64)
    rank[comp[np.sort(first)]] = np.arange(first.size)
    return rank[comp]


# -- JSON polygons ----------------------------------------------------------------------
def write_polygons_json(path, polygons, ids=None):
    """Write 2D bubbles as JSON ``{"units": "mm", "bubbles": [{"id", "attenuation", "vertices"}]}``.

    Parameters
    ----------
    path : str or os.PathLike
    polygons : sequence of Polygon (or SubdivisionSurface, written refined)
        Counter-clockwise (as Polygon guarantees).
    ids : sequence of int, optional
        Default ``0..n-1``.

    Returns
    -------
    pathlib.Path
    """
    ps = _resolve(polygons, Polygon, "polygons")
    bid = _ids(ids, len(ps))
    doc = {
        "units": "mm",
        "bubbles": [
            {"id": i, "attenuation": float(pg.attenuation), "vertices": pg.vertices.tolist()}
            for i, pg in zip(bid, ps)
        ],
    }
    with atomic_open(path, "w") as fh:
        json.dump(doc, fh, indent=None, separators=(",", ":"))
        fh.write("\n")
    return Path(path)


def read_polygons_json(path, attenuation=None, *, with_ids=False):
    """Read 2D bubbles written by :func:`write_polygons_json` (or by hand).

    Parameters
    ----------
    path : str or os.PathLike
    attenuation : float, optional
        Attenuation of every bubble; overrides the file's per-bubble
        ``attenuation``, and is required where a bubble has none.
    with_ids : bool
        Also return the ids.

    Returns
    -------
    polygons : list of Polygon
        In file order. A last vertex equal to the first is dropped.
    ids : list of int
        Only with ``with_ids=True``.

    Raises
    ------
    ValueError
        On invalid JSON, a missing ``bubbles`` list, a bubble without an
        integer ``id`` or with duplicate id, fewer than 3 vertices,
        non-numeric or non-finite coordinates, clockwise vertices, or no
        attenuation.
    """
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p.name}: invalid JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("bubbles"), list):
        raise ValueError(f"{p.name}: expected an object with a 'bubbles' list")
    polys, ids = [], []
    for k, b in enumerate(doc["bubbles"]):
        if not isinstance(b, dict):
            raise ValueError(f"{p.name}: bubbles[{k}] is not an object")
        i = b.get("id")
        if isinstance(i, bool) or not isinstance(i, int):
            raise ValueError(f"{p.name}: bubbles[{k}] has no integer 'id'")
        if i in ids:
            raise ValueError(f"{p.name}: duplicate bubble id {i}")
        where = f"{p.name}: bubble {i}"
        try:
            v = np.array(b.get("vertices"), dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{where}: 'vertices' must be a list of [x, y] numbers") from None
        if v.ndim != 2 or v.shape[1] != 2:
            raise ValueError(f"{where}: 'vertices' must be a list of [x, y] pairs, got shape {v.shape}")
        if len(v) > 3 and np.array_equal(v[0], v[-1]):
            v = v[:-1]
        if len(v) < 3:
            raise ValueError(f"{where}: needs at least 3 vertices, got {len(v)}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{where}: vertices contain NaN or inf")
        x, y = v.T
        signed = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
        if signed <= 0:
            raise ValueError(f"{where}: vertices are clockwise or degenerate; give them counter-clockwise")
        mu = attenuation if attenuation is not None else b.get("attenuation")
        if mu is None:
            raise ValueError(f"{where}: no 'attenuation'; pass attenuation=")
        try:
            polys.append(Polygon(v, mu))
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        ids.append(i)
    return (polys, ids) if with_ids else polys


# -- tables --------------------------------------------------------------------------------
def bubble_table(items, ids=None):
    """Per-bubble measurements.

    Parameters
    ----------
    items : sequence of Mesh or of Polygon (or SubdivisionSurface, measured refined)
    ids : sequence of int, optional
        Default ``0..n-1``.

    Returns
    -------
    list of dict
        2D rows have :data:`BUBBLE_COLUMNS_2D` (``equivalent_diameter_mm =
        2 sqrt(area / pi)``); 3D rows have :data:`BUBBLE_COLUMNS_3D`
        (``equivalent_diameter_mm = (6 volume / pi)^(1/3)``); units and
        meanings in :data:`BUBBLE_COLUMN_INFO`.
    """
    if isinstance(items, (Mesh, Polygon)) or hasattr(items, "fine"):
        items = [items]
    items = list(items)
    resolved = [it.fine() if not isinstance(it, (Mesh, Polygon)) and hasattr(it, "fine") else it for it in items]
    if not resolved:
        return []
    if all(isinstance(it, Polygon) for it in resolved):
        want = Polygon
    elif all(isinstance(it, Mesh) for it in resolved):
        want = Mesh
    else:
        kinds = sorted({type(it).__name__ for it in resolved})
        raise ValueError(f"items must be all Mesh or all Polygon, got {kinds}")
    resolved = _resolve(resolved, want, "items")
    bid = _ids(ids, len(resolved))
    rows = []
    for i, it in zip(bid, resolved):
        c = np.asarray(it.centroid, dtype=float)
        if want is Polygon:
            a = float(it.area)
            values = (i, c[0], c[1], a, it.perimeter, 2.0 * np.sqrt(max(a, 0.0) / np.pi))
            rows.append(dict(zip(BUBBLE_COLUMNS_2D, (i, *map(float, values[1:])))))
        else:
            v = float(it.volume)
            values = (c[0], c[1], c[2], v, it.area, np.cbrt(6.0 * max(v, 0.0) / np.pi))
            rows.append(dict(zip(BUBBLE_COLUMNS_3D, (i, *map(float, values)))))
    return rows


def csv_metadata_path(path):
    """The sidecar of a CSV file: ``bubbles.csv`` -> ``bubbles.csv-metadata.json`` (the CSVW convention)."""
    p = Path(path)
    return p.with_name(p.name + "-metadata.json")


def _csv_metadata(path, columns, info, title):
    cols = []
    for c in columns:
        if c not in info:
            raise ValueError(f"column {c!r} has no (unit, meaning) in the column descriptions")
        unit, meaning = info[c]
        entry = {"name": c, "titles": c, "dc:description": meaning}
        if unit:
            entry["unit"] = unit
        cols.append(entry)
    doc = {"@context": "http://www.w3.org/ns/csvw", "url": Path(path).name, "dc:title": title,
           "dialect": {"header": True}, "tableSchema": {"columns": cols}}
    return json.dumps(doc, indent=2) + "\n"


def write_csv(path, rows, columns=None, *, describe=None, title=None):
    """Write rows (dicts) as CSV with a header line, atomically, and optionally its column sidecar.

    Parameters
    ----------
    path : str or os.PathLike
    rows : sequence of dict
        All with the same keys.
    columns : sequence of str, optional
        Column order; defaults to the keys of the first row. With no rows
        and no columns, an empty file is written.
    describe : dict, optional
        ``{column: (unit, meaning)}`` for every column (e.g.
        :data:`BUBBLE_COLUMN_INFO`); then the sidecar
        :func:`csv_metadata_path` is written too (W3C CSV on the Web
        metadata: name, unit, description of each column).
    title : str, optional
        Title of the table in the sidecar.

    Returns
    -------
    pathlib.Path
    """
    rows = list(rows)
    if columns is None:
        columns = list(rows[0].keys()) if rows else []
    columns = [str(c) for c in columns]
    for k, r in enumerate(rows):
        if not isinstance(r, dict):
            raise ValueError(f"rows[{k}] is not a dict")
        if set(r) != set(columns):
            missing = sorted(set(columns) - set(r))
            extra = sorted(set(r) - set(columns))
            raise ValueError(f"rows[{k}] keys differ from the columns (missing {missing}, extra {extra})")
    # described before anything is written, so an undescribed column writes neither file
    meta = None if describe is None else _csv_metadata(path, columns, describe, title or Path(path).stem)
    with atomic_open(path, "w", newline="") as fh:
        if columns:
            w = csv.DictWriter(fh, fieldnames=columns, lineterminator="\n")
            w.writeheader()
            for r in rows:
                w.writerow({k: (repr(float(v)) if isinstance(v, (float, np.floating)) else v) for k, v in r.items()})
    if meta is not None:
        with atomic_open(csv_metadata_path(path), "w") as fh:
            fh.write(meta)
    return Path(path)
