"""Pictures of a reconstruction, written off-screen (matplotlib Agg, no display needed).

- :func:`write_overlay`: the voxel preview with the bubble outlines; in 3D three
  orthogonal slices (xy, xz, yz through the middle) with the meshes' cross-sections.
- :func:`write_mesh_view`: a shaded 3D rendering of the bubble meshes, coloured by id.
- :func:`write_size_histogram`: the distribution of equivalent diameters.
- :func:`write_figures`: the three of them for ``bubsub reconstruct``'s output folder.

Every image has axes in mm and a colour bar saying what its colours mean;
bubbles keep one colour (by id) across the pictures.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bubsub.core.io.atomic import atomic_path

from bubsub.clients.progress import phase

__all__ = ["mesh_section", "subplots", "write_overlay", "write_mesh_view", "write_size_histogram", "write_figures"]

_AXES = "xyz"
#: Preview values are |bubble_contrast| inside bubbles, 0 in the liquid.
_PREVIEW_LABEL = "voxel preview: bubble density (1/mm, |contrast| inside bubbles)"


def _figure(**kw):
    # A bare Figure renders with Agg and leaves pyplot alone: writing pictures from a
    # notebook does not switch its backend off inline plots.
    from matplotlib.figure import Figure

    return Figure(**kw)


def subplots(*grid, figsize=None, dpi=None, **kw):
    """``(figure, axes)`` like ``pyplot.subplots``, on a bare Figure: pyplot's backend is left alone
    (a notebook's inline plots keep working after bubsub writes a picture)."""
    fig = _figure(figsize=figsize, dpi=dpi)
    return fig, fig.subplots(*grid, **kw)


def _save(fig, path, tight=True):
    # ``tight`` crops to the drawn artists, which costs a second draw of the figure
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", bbox_inches="tight" if tight else None)


def _id_colours(ids):
    """One colour per bubble id (tab20, cycling), and the colour map and norm for a colour bar."""
    from matplotlib import colormaps
    from matplotlib.colors import BoundaryNorm, ListedColormap

    base = colormaps["tab20"]
    ids = list(ids)
    colours = [base(int(i) % 20) for i in ids]
    lo, hi = (min(ids), max(ids)) if ids else (0, 1)
    cmap = ListedColormap([base(int(i) % 20) for i in range(lo, hi + 1)])
    norm = BoundaryNorm(np.arange(lo - 0.5, hi + 1.5), cmap.N)
    return colours, cmap, norm


def _id_colourbar(fig, ax, ids, cmap, norm, cax=None):
    from matplotlib.cm import ScalarMappable

    mappable = ScalarMappable(norm=norm, cmap=cmap)
    bar = fig.colorbar(mappable, cax=cax) if cax is not None else fig.colorbar(mappable, ax=ax, shrink=0.7, pad=0.14)
    bar.set_label("bubble id")
    ids = sorted(ids)
    if len(ids) > 12:  # a readable number of ticks
        ids = ids[:: int(np.ceil(len(ids) / 12))]
    bar.set_ticks(ids)
    return bar


def mesh_section(mesh, axis, value):
    """Segments where the plane ``coordinate[axis] = value`` cuts a triangle mesh.

    Parameters
    ----------
    mesh : Mesh
    axis : {0, 1, 2}
        x, y or z.
    value : float, mm

    Returns
    -------
    (k, 2, 2) float
        Segment end points in the two remaining coordinates, in x, y, z order
        (``(x, y)`` for a z plane, ``(x, z)`` for a y plane, ``(y, z)`` for an x plane).
    """
    keep = [a for a in range(3) if a != axis]
    tri = mesh.vertices[np.asarray(mesh.faces)]  # (m, 3, 3)
    h = tri[:, :, axis] - value
    above = h > 0
    cut = above.sum(axis=1) % 3 != 0
    tri, h, above = tri[cut], h[cut], above[cut]
    # a cut triangle has exactly two edges whose ends lie on opposite sides: their points, in edge order
    # (0-1, 1-2, 2-0), whole arrays at once (a loop over the cut triangles would take a third of a picture's time)
    i, j = np.array([0, 1, 2]), np.array([1, 2, 0])
    crosses = above[:, i] != above[:, j]
    with np.errstate(divide="ignore", invalid="ignore"):  # edges that do not cross are discarded below
        t = h[:, i] / (h[:, i] - h[:, j])
        pts = tri[:, i] + t[:, :, None] * (tri[:, j] - tri[:, i])  # (k, 3 edges, 3)
    first = np.argsort(~crosses, axis=1, kind="stable")[:, :2]
    return pts[np.arange(len(tri))[:, None], first][:, :, keep]


def _slices(image, extent):
    """The three middle slices of a ``(z, y, x)`` preview, each with its plane and imshow arguments."""
    nz, ny, nx = image.shape
    x0, x1, y0, y1, z0, z1 = extent
    kz, ky, kx = nz // 2, ny // 2, nx // 2
    z = z0 + (kz + 0.5) * (z1 - z0) / nz
    y = y1 - (ky + 0.5) * (y1 - y0) / ny  # row 0 is at y max
    x = x0 + (kx + 0.5) * (x1 - x0) / nx
    return [
        ("xy", 2, z, image[kz], (x0, x1, y0, y1), "upper"),
        ("xz", 1, y, image[:, ky, :], (x0, x1, z0, z1), "lower"),
        ("yz", 0, x, image[:, ::-1, kx], (y0, y1, z0, z1), "lower"),  # columns flipped to increasing y
    ]


def write_overlay(path, image, extent, fine_items, ids=None, title="BubSub reconstruction on the voxel preview"):
    """PNG of the voxel preview with the reconstructed bubble outlines (3D: three orthogonal slices).

    Parameters
    ----------
    path : str or os.PathLike
    image : ndarray, ``(rows, cols)`` or ``(slices, rows, cols)``
        :func:`bubsub.clients.pipeline.static.preview.voxel_preview`.
    extent : tuple
        ``(xmin, xmax, ymin, ymax[, zmin, zmax])``, mm.
    fine_items : list of Polygon or Mesh
    ids : list of int, optional
        Bubble ids (outline colours); default ``0..n-1``.
    """
    from matplotlib.collections import LineCollection

    ids = list(range(len(fine_items))) if ids is None else list(ids)
    colours, _, _ = _id_colours(ids)
    vmax = float(np.max(image)) if image.size and np.max(image) > 0 else 1.0
    if image.ndim == 2:
        fig = _figure(figsize=(7.5, 6.5), dpi=110)
        ax = fig.subplots()
        shown = ax.imshow(image, extent=extent, cmap="gray", origin="upper", vmin=0, vmax=vmax)
        for p, c in zip(fine_items, colours):
            xy = np.vstack([p.vertices, p.vertices[:1]])
            ax.plot(xy[:, 0], xy[:, 1], color=c, lw=1.2)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(title, fontsize=10)
        fig.colorbar(shown, ax=ax, shrink=0.8).set_label(_PREVIEW_LABEL)
        _save(fig, path)
        return
    # fixed margins, drawn once: constrained layout and a tight box each cost a draw (a second of the run)
    fig = _figure(figsize=(16, 5.6), dpi=100)
    fig.subplots_adjust(left=0.04, right=0.9, bottom=0.1, top=0.86, wspace=0.22)
    axes = fig.subplots(1, 3)
    for ax, (name, axis, value, sl, ext, origin) in zip(axes, _slices(image, extent)):
        shown = ax.imshow(sl, extent=ext, cmap="gray", origin=origin, vmin=0, vmax=vmax)
        segs = [mesh_section(m, axis, value) for m in fine_items]
        cols = [c for s, c in zip(segs, colours) for _ in range(len(s))]
        if cols:
            ax.add_collection(LineCollection(np.concatenate(segs), colors=cols, linewidths=1.2))
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_xlabel(f"{name[0]} (mm)")
        ax.set_ylabel(f"{name[1]} (mm)")
        ax.set_title(f"{name} slice, {_AXES[axis]} = {value:.2f} mm", fontsize=10)
    fig.colorbar(shown, cax=fig.add_axes((0.915, 0.14, 0.012, 0.68))).set_label(_PREVIEW_LABEL)
    fig.suptitle(f"{title}: orthogonal slices with the meshes' cross-sections (colour = bubble id)", fontsize=11)
    _save(fig, path, tight=False)


def write_mesh_view(path, meshes, ids=None, title="BubSub bubble meshes", elevation=25, azimuth=-60):
    """Shaded off-screen rendering of 3D bubble meshes, one colour per bubble id (mplot3d).

    Parameters
    ----------
    path : str or os.PathLike
    meshes : list of Mesh
        E.g. the refined surfaces (pass the control meshes for very many bubbles:
        mplot3d draws every face).
    ids : list of int, optional
    elevation, azimuth : float
        View angles in degrees.
    """
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    ids = list(range(len(meshes))) if ids is None else list(ids)
    colours, cmap, norm = _id_colours(ids)
    fig = _figure(figsize=(8, 7), dpi=100)
    # fixed margins: a tight bounding box costs a second draw of every face
    ax = fig.add_axes((0.0, 0.03, 0.8, 0.9), projection="3d")
    light = np.array([0.4, -0.5, 0.77])
    light /= np.linalg.norm(light)
    tris, faces_rgb = [], []
    for m, c in zip(meshes, colours):
        tri = m.vertices[np.asarray(m.faces)]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        shade = 0.35 + 0.65 * np.clip(n @ light, 0, 1)
        tris.append(tri)
        faces_rgb.append(np.clip(np.asarray(c[:3])[None, :] * shade[:, None], 0, 1))
    if tris:
        # one collection: mplot3d orders faces by depth within a collection but draws
        # collections whole, so one per bubble let far bubbles cover near ones
        tri = np.concatenate(tris)
        ax.add_collection3d(Poly3DCollection(tri, facecolors=np.concatenate(faces_rgb), edgecolors="none"))
        lo, hi = tri.reshape(-1, 3).min(axis=0), tri.reshape(-1, 3).max(axis=0)
        for setter, a, b in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), lo, hi):
            setter(a, b)
        ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-9)))
    ax.view_init(elev=elevation, azim=azimuth)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title(f"{title} ({len(meshes)} bubbles)", fontsize=10)
    if ids:
        _id_colourbar(fig, ax, ids, cmap, norm, cax=fig.add_axes((0.88, 0.2, 0.02, 0.6)))
    _save(fig, path, tight=False)


def write_size_histogram(path, diameters, ndim, title="Bubble size distribution"):
    """Histogram of equivalent diameters (mm), with their mean and standard deviation.

    Parameters
    ----------
    diameters : (n,) float, mm
        ``equivalent_diameter_mm`` of :func:`bubsub.core.analysis.shape.bubble_table`.
    ndim : {2, 3}
        Says whether a diameter is that of a disc of equal area or a ball of equal volume.
    """
    d = np.asarray(diameters, dtype=float)
    fig = _figure(figsize=(7, 4.5), dpi=100)
    ax = fig.subplots()
    if d.size:
        # sizes equal to the last bits (a monodisperse foam) span no finite bins: give them a range of their own
        lim = None
        if np.ptp(d) <= 1e-9 * max(1.0, float(np.abs(d).max())):
            half = 0.05 * max(abs(float(d.mean())), 1e-3)
            lim = (d.mean() - half, d.mean() + half)
        ax.hist(d, bins=max(5, min(40, int(np.sqrt(d.size)) + 3)), range=lim, color="tab:blue", edgecolor="white")
        ax.axvline(d.mean(), color="tab:orange", lw=1.5, label=f"mean {d.mean():.3g} mm")
        ax.legend(fontsize=9)
    shape = "disc of equal area" if ndim == 2 else "ball of equal volume"
    ax.set_xlabel(f"equivalent diameter (mm; {shape})")
    ax.set_ylabel("number of bubbles")
    ax.yaxis.get_major_locator().set_params(integer=True)
    spread = f", mean {d.mean():.3g} mm, s.d. {d.std():.2g} mm" if d.size else ""
    ax.set_title(f"{title}: {d.size} bubbles{spread}", fontsize=10)
    _save(fig, path)


def write_figures(out, rec, fine, rows, *, progress=False):
    """Write ``overlay.png`` (preview slices with outlines), ``sizes.png`` and, in 3D, ``meshes.png``.

    Parameters
    ----------
    out : str or os.PathLike
        An existing folder.
    rec : bubsub.clients.pipeline.reconstruct.Reconstruction
        Its ``preview`` (None: no overlay), ``preview_extent``, ``surfaces`` and ``report["dimension"]``.
    fine : list of Mesh or Polygon
        The subdivided surfaces of ``rec.surfaces``.
    rows : list of dict
        :func:`bubsub.core.analysis.shape.bubble_table` of ``fine`` (ids and equivalent diameters).
    progress : bool
        Show the pictures as a phase.

    Returns
    -------
    dict of str to pathlib.Path
        ``{"overlay", "sizes", ["meshes"]}``.
    """
    out = Path(out)
    ids = [r["id"] for r in rows]
    files = {}
    three_d = rec.report["dimension"] == 3
    total = 1 + (rec.preview is not None) + three_d
    with phase("pictures", total, unit="picture", enabled=progress) as bar:
        if rec.preview is not None:
            files["overlay"] = out / "overlay.png"
            write_overlay(files["overlay"], rec.preview, rec.preview_extent, fine, ids)
            bar.update()
        files["sizes"] = out / "sizes.png"
        write_size_histogram(files["sizes"], [r["equivalent_diameter_mm"] for r in rows
                                              if r["equivalent_diameter_mm"] != ""], rec.report["dimension"])
        bar.update()
        if three_d:
            # mplot3d draws every face: very many bubbles are shown by their control meshes
            shown = fine if sum(len(m.faces) for m in fine) <= 60000 else [s.control for s in rec.surfaces]
            files["meshes"] = out / "meshes.png"
            write_mesh_view(files["meshes"], shown, ids)
            bar.update()
    return files
