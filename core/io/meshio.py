"""Bubble meshes (PLY, through plyfile) and bubble polygons (JSON).

Formats
-------
PLY (3D)
    All bubbles in one file (binary little-endian by default, or ASCII):
    ``vertex`` with ``double x, y, z`` (mm), ``face`` with
    ``list uchar int vertex_indices``, ``int bubble_id`` and
    ``double attenuation`` (1/mm). MeshLab, ParaView, trimesh and other PLY
    readers open it; extra face properties are ignored by readers that do
    not know them. :func:`read_ply` groups the faces by ``bubble_id`` (or,
    in files without it, by connected component). Files are read and their
    headers written by plyfile; the binary face records, whose layout that
    header fixes, are written as one numpy array (plyfile writes list
    properties row by row, some 16 us a face: a minute for a 3-million-face
    truth file).
JSON (2D)
    ``{"units": "mm", "bubbles": [{"id": int, "attenuation": float,
    "vertices": [[x, y], ...]}, ...]}``, vertices counter-clockwise, the
    first vertex not repeated at the end.

The bubble tables (CSV) are in :mod:`bubsub.core.io.tables`.
All writers are atomic (:mod:`bubsub.core.io.atomic`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from plyfile import PlyData, PlyElement, PlyElementParseError, PlyHeaderParseError

from bubsub.core.io.atomic import atomic_open
from bubsub.core.projection.items import bubble_ids, resolve_items
from bubsub.core.projection.mesh import Mesh, Polygon

__all__ = ["write_ply", "read_ply", "write_polygons_json", "read_polygons_json"]

#: The face records of :func:`write_ply`: three vertex indices (a PLY list of length 3), id, attenuation.
FACE_DTYPE = np.dtype([("vertex_indices", "<i4", (3,)), ("bubble_id", "<i4"), ("attenuation", "<f8")])
#: The same records as stored in a binary file: the list's length byte before its indices.
_FACE_DTYPE_BINARY = np.dtype([("n", "u1"), ("vertex_indices", "<i4", (3,)), ("bubble_id", "<i4"),
                               ("attenuation", "<f8")])
_VERTEX_DTYPE = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8")])
#: Names other tools give the face index list.
_INDEX_NAMES = ("vertex_indices", "vertex_index")


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
        Binary little-endian (default) or ASCII (every double written with
        18 significant digits, so both read back exactly).

    Returns
    -------
    pathlib.Path
    """
    ms = resolve_items(meshes, Mesh, "meshes")
    bid = bubble_ids(ids, len(ms))
    if any(not -(2**31) <= i < 2**31 for i in bid):
        raise ValueError("ids must fit in a 32-bit signed integer")
    counts = [len(m.vertices) for m in ms]
    if sum(counts) >= 2**31:
        raise ValueError("too many vertices for a PLY file with int indices")
    vertex = np.zeros(sum(counts), _VERTEX_DTYPE)
    if ms:
        xyz = np.concatenate([m.vertices for m in ms])
        vertex["x"], vertex["y"], vertex["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    n_faces = [len(m.faces) for m in ms]
    face = np.zeros(sum(n_faces), FACE_DTYPE)
    if ms:
        offsets = np.cumsum([0] + counts[:-1])
        face["vertex_indices"] = np.concatenate([np.asarray(m.faces) + o for m, o in zip(ms, offsets)])
        face["bubble_id"] = np.repeat(np.array(bid, dtype=np.int64), n_faces)
        face["attenuation"] = np.repeat(np.array([m.attenuation for m in ms], dtype=np.float64), n_faces)
    ply = PlyData([PlyElement.describe(vertex, "vertex"),
                   PlyElement.describe(face, "face", len_types={"vertex_indices": "u1"})],
                  text=not binary, byte_order="<", comments=["bubsub bubble meshes; units mm, attenuation 1/mm"])
    with atomic_open(path, "wb") as fh:
        if not binary:
            ply.write(fh)
        else:
            fh.write((ply.header + "\n").encode("ascii"))
            fh.write(vertex.tobytes())
            records = np.zeros(len(face), _FACE_DTYPE_BINARY)
            records["n"] = 3
            for name in FACE_DTYPE.names:
                records[name] = face[name]
            fh.write(records.tobytes())
    return Path(path)


def _read_ply_arrays(p):
    """``(vertices (n, 3) float64, faces (m, 3) int64, face properties {name: (m,) array})`` of a triangle PLY."""
    try:
        with open(p, "rb") as fh:
            ply = PlyData.read(fh, known_list_len={"face": {name: 3 for name in _INDEX_NAMES}})
            names = [e.name for e in ply.elements]
            for need in ("vertex", "face"):
                if need not in names:
                    raise ValueError(f"{p.name}: PLY file has no '{need}' element")
            vx, fc = ply["vertex"].data, ply["face"].data
            if not all(k in vx.dtype.names for k in "xyz"):
                raise ValueError(f"{p.name}: PLY vertices need properties x, y and z")
            verts = np.stack([vx["x"], vx["y"], vx["z"]], axis=1).astype(np.float64)
            key = next((k for k in _INDEX_NAMES if k in fc.dtype.names), None)
            if key is None:
                raise ValueError(f"{p.name}: PLY faces need a list property 'vertex_indices'")
            lists = fc[key]
            if lists.dtype == object:  # ASCII (or an unknown list layout): one array per face
                if any(len(f) != 3 for f in lists):
                    raise ValueError(f"{p.name}: only triangle faces are supported")
                faces = np.array([np.asarray(f) for f in lists], dtype=np.int64).reshape(-1, 3)
            else:
                faces = np.array(lists, dtype=np.int64).reshape(-1, 3)
            props = {k: np.array(fc[k]) for k in fc.dtype.names if k != key}
    except PlyHeaderParseError as exc:
        raise ValueError(f"{p.name} is not a PLY file ({exc})") from None
    except PlyElementParseError as exc:
        if "list length" in str(exc):
            raise ValueError(f"{p.name}: only triangle faces are supported") from None
        if "end-of-file" in str(exc):
            raise ValueError(f"{p.name}: PLY file is truncated ({exc})") from None
        raise ValueError(f"{p.name}: malformed PLY data ({exc})") from None
    return verts, faces, props


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
        If the file is not a (triangle) PLY, is truncated, lacks vertex/face
        elements, indices are out of range, a bubble is not a closed outward
        mesh, a bubble's faces disagree on attenuation, or no attenuation is
        known.
    """
    p = Path(path)
    verts, faces, fc = _read_ply_arrays(p)
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
    from scipy.sparse.csgraph import connected_components  # heavy: not at `import bubsub.core`

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
    ps = resolve_items(polygons, Polygon, "polygons")
    bid = bubble_ids(ids, len(ps))
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
