"""Work on a few bubbles with the rest of the scene held fixed: footprints, detector windows, local refits.

A bubble shadows a small part of the detector. Once the whole scene's
residual ``r = Proj(all) - d`` is known, a change to a few bubbles needs only
their own projections (:class:`Footprint`, stored on their support) and a
projector onto a detector window around them (:class:`Window`): the target
of a local fit is the data minus every other bubble, ``own - r`` on the
window, and its cost follows the pixels the changed bubbles shadow, not the
scan's. :func:`local_refit` refits the bubbles a topology change or a repair
touched (and their neighbours) that way, instead of the whole scene.
"""

from __future__ import annotations

import numpy as np

from bubsub.clients.optimise.fit import fit
from bubsub.clients.progress import phase
from bubsub.core import MeshProjector, ScanGeometry

__all__ = ["Footprint", "Footprints", "Window", "footprint", "scene_residual", "scene_objective", "others_removed", "local_fits",
           "local_refit", "touching_groups", "LOCAL_RTOL"]


class Footprint:
    """One bubble's own projection, stored on its support only.

    A bubble shadows a small part of the detector; keeping one dense float64
    projection per bubble cost 60 x 26 MB on a 25 x 256 x 512 scan and set
    the pipeline's peak memory.
    """

    __slots__ = ("index", "values")

    def __init__(self, projection):
        flat = np.asarray(projection).ravel()
        self.index = np.flatnonzero(flat)
        self.values = flat[self.index].astype(np.float64)

    @classmethod
    def from_window(cls, part, starts, full_shape):
        """From a projection onto a detector window (:meth:`ScanGeometry.window`) starting at ``starts``
        (row starts, column starts) of a detector of projections ``full_shape``."""
        fp = cls.__new__(cls)
        nz = np.nonzero(part)
        fp.values = part[nz].astype(np.float64)
        if len(full_shape) == 3:
            p, r, c = nz
            fp.index = (p * full_shape[1] + starts[0][p] + r) * full_shape[2] + starts[1][p] + c
        else:
            p, c = nz
            fp.index = p * full_shape[1] + starts[1][p] + c
        return fp

    def add_to(self, array, sign=1.0):
        """``array += sign * p`` in place (``array`` C-contiguous, the projection's shape)."""
        array.reshape(-1)[self.index] += sign * self.values

    def removal_gain(self, residual):
        """``0.5 ||r - p||^2 - 0.5 ||r||^2`` without forming ``r - p``."""
        return 0.5 * float(self.values @ self.values) - float(residual.reshape(-1)[self.index] @ self.values)

    def removal_gains(self, residual):
        """:meth:`removal_gain` per projection (the residual's first axis): ``(views,)`` float."""
        per_view = int(np.prod(residual.shape[1:]))
        term = self.values * (0.5 * self.values - residual.reshape(-1)[self.index])
        return np.bincount(self.index // per_view, weights=term, minlength=residual.shape[0])

    def addition_gain(self, residual):
        """``0.5 ||r + p||^2 - 0.5 ||r||^2`` without forming ``r + p``."""
        return 0.5 * float(self.values @ self.values) + float(residual.reshape(-1)[self.index] @ self.values)


class Window:
    """A detector window around some bubbles' shadows, and a projector onto it.

    A bubble shadows a small part of the detector, but a projection and an
    objective over the whole detector cost a pass over every pixel: the
    local fits of a merge or split spent most of their time there (25 ms per
    evaluation of one bubble on a 25 x 256 x 512 scan). The window is the
    bounding box of the shadows in each projection, grown by ``margin`` of
    its size and ``pad`` pixels so that the bubbles can move and grow, the
    same size in every projection (one geometry); the whole detector when
    that would be most of it. Objectives on one window are comparable with
    each other: outside it they differ by the same constant.
    """

    def __init__(self, projector, surfaces, margin=0.3, pad=3):
        g = projector.geometry
        self.projector, self.starts, self.size, self.full_shape = projector, None, None, g.shape
        col, row, ahead = g.detector_coordinates(np.concatenate([s.fine().vertices for s in surfaces]))
        if not ahead.all():
            return
        starts, size = [], []
        for coord, n in ((row, g.det_rows), (col, g.det_cols)) if g.ndim == 3 else ((col, g.det_cols),):
            lo, hi = coord.min(axis=1) + 0.5 * n, coord.max(axis=1) + 0.5 * n  # pixel edges
            width = int(np.ceil((hi - lo).max() * (1 + 2 * margin))) + 2 * pad
            width = min(width, n)
            starts.append(np.clip(np.round(0.5 * (lo + hi) - 0.5 * width), 0, n - width).astype(np.int64))
            size.append(width)
        if np.prod(size) > 0.5 * np.prod(g.shape[1:]):
            return
        if g.ndim == 2:
            starts, size = [0] + starts, [None] + size
        self.starts, self.size = starts, size
        self.projector = MeshProjector(g.window(starts[0], starts[1], size[0], size[1]),
                                       supersampling=projector.supersampling, threads=projector.threads,
                                       backend=projector.backend)

    @property
    def pixels(self):
        """Pixels of the window over all projections (the whole detector's when it is no window)."""
        return int(np.prod(self.projector.geometry.shape))

    def cut(self, projections):
        """The window's part of whole-detector projections."""
        if self.starts is None:
            return projections

        return ScanGeometry.window_of(projections, self.starts[0], self.starts[1], self.size[0], self.size[1])

    def footprint(self, surface):
        """``surface``'s own projection (all of it inside the window) as a whole-detector :class:`Footprint`."""
        part = self.projector.forward([surface])
        if self.starts is None:
            return Footprint(part)
        return Footprint.from_window(part, self.starts, self.full_shape)


def footprint(projector, surface):
    """``surface``'s own projection by ``projector`` as a :class:`Footprint`, projected onto a window around
    its shadow (:class:`Window`): the cost and memory of its pixels, not of the detector's."""
    return Window(projector, [surface]).footprint(surface)


class Footprints:
    """The bubbles of a scene and their own projections, each computed when first asked for.

    A scene's footprints together are the size of its whole projection
    times the bubbles one ray crosses (about 1 GB for 600 bubbles on a
    40 x 256 x 768 scan): a topology round asks for those of a few
    candidates only, so only those are kept.

    Parameters
    ----------
    projector : MeshProjector
    surfaces : list of SubdivisionSurface
    """

    def __init__(self, projector, surfaces):
        self.projector = projector
        self.surfaces = list(surfaces)
        self._kept = [None] * len(self.surfaces)

    def __len__(self):
        return len(self.surfaces)

    def __getitem__(self, k):
        """Bubble ``k``'s :class:`Footprint` (computed now and kept, if not yet)."""
        if self._kept[k] is None:
            self._kept[k] = self.compute(k)
        return self._kept[k]

    def compute(self, k):
        """Bubble ``k``'s :class:`Footprint`, not kept."""
        if self._kept[k] is not None:
            return self._kept[k]
        return footprint(self.projector, self.surfaces[k])

    def set(self, k, surface, footprint=None):
        """Replace bubble ``k`` (its footprint given, or computed when asked for)."""
        self.surfaces[k], self._kept[k] = surface, footprint

    def append(self, surface, footprint=None):
        self.surfaces.append(surface)
        self._kept.append(footprint)

    def subset(self, keep):
        """The bubbles ``keep`` (indices), with what is kept of their footprints."""
        out = Footprints(self.projector, [self.surfaces[k] for k in keep])
        out._kept = [self._kept[k] for k in keep]
        return out


def scene_residual(projector, surfaces, data):
    """``Proj(surfaces) - data`` in float64, formed in place: one array of the detector's size beside the
    float32 projection, where ``forward(...).astype(float) - data`` held two."""
    if not surfaces:
        return -np.asarray(data, dtype=np.float64)
    residual = projector.forward(surfaces).astype(np.float64)
    residual -= data
    return residual


def scene_objective(projector, surfaces, data):
    """``0.5 ||Proj(surfaces) - data||^2`` from a projection (:func:`scene_residual`), no gradient."""
    residual = scene_residual(projector, surfaces, data)
    return 0.5 * float(np.vdot(residual, residual))


def others_removed(residual, *own):
    """``data`` minus every bubble but ``own``: ``sum(own) - residual``."""
    target = -residual
    for o in own:
        o.add_to(target)
    return target


def local_fits(projector, candidates, target, iterations):
    """Each candidate set of bubbles fitted alone to ``target`` on one detector window around all of
    them: ``[(surfaces, objective), ...]``, objectives comparable with each other."""
    window = Window(projector, [s for items in candidates for s in items])
    part = np.ascontiguousarray(window.cut(target))
    out = []
    for items in candidates:
        res = fit(window.projector, items, part, iterations=iterations, progress=False, catch_interrupt=False)
        out.append((res.surfaces, res.objective))
    return out


#: A refit of :func:`local_refit` stops once :data:`~bubsub.clients.optimise.fit.STALL_ITERATIONS` iterations have
#: lowered its objective by less than this fraction of it: the static fit's own test (``fit_rtol``). Its
#: bubbles start near their optimum, and a fit without the test runs to its cap: on the flowing foam of
#: ``bubsub bench dynamic`` the last half of a 40-iteration refit lowers its objective by about 0.05 %.
LOCAL_RTOL = 2e-4

#: Most bubbles refitted together on one window by :func:`local_refit`: groups of changed bubbles that share
#: neighbours are merged up to this size (a dense foam's neighbourhoods would otherwise join into one).
MAX_GROUP = 24


def _spheres(surfaces):
    fines = [s.fine().vertices for s in surfaces]
    centres = np.array([v.mean(axis=0) for v in fines])
    radii = np.array([np.linalg.norm(v - c, axis=1).max() for v, c in zip(fines, centres)])
    return centres, radii


def touching_groups(surfaces, changed, touch, *, near=()):
    """Groups of bubbles to refit together: each changed bubble with the bubbles whose bounding spheres
    come within ``touch`` of its own, groups sharing a bubble merged while at most :data:`MAX_GROUP`.

    Parameters
    ----------
    surfaces : list of SubdivisionSurface
    changed : iterable of int
        Indices into ``surfaces``.
    touch : float
        mm.
    near : sequence of (centre (ndim,), radius)
        Places where bubbles were removed: the bubbles around them join the refit (they may fill the gas).

    Returns
    -------
    list of sorted lists of int
    """
    if not surfaces:
        return []
    centres, radii = _spheres(surfaces)
    stars = []
    for c, r in [(centres[k], radii[k]) for k in sorted(set(changed))] + [tuple(x) for x in near]:
        d = np.linalg.norm(centres - np.asarray(c), axis=1)
        members = set(np.nonzero(d <= radii + float(r) + touch)[0].tolist())
        if members:
            stars.append(members)
    groups = []
    for star in stars:
        for g in groups:
            if g & star and len(g | star) <= MAX_GROUP:
                g |= star
                break
        else:
            groups.append(set(star))
    return [sorted(g) for g in groups]


def local_refit(projector, surfaces, data, changed, *, iterations, touch, near=(), residual=None, penalty=None,
                progress=False, label="local refit", rtol=LOCAL_RTOL):
    """Refit the bubbles ``changed`` and their neighbours, the rest held fixed.

    Each group of :func:`touching_groups` is fitted alone to the data minus
    every other bubble on a window around it (:class:`Window`), one group
    after another, the residual updated after each: the cost follows the
    pixels the groups shadow, not the scan's size. When the groups' windows
    together hold more pixels than the scan (a repair that touched a large
    part of a dense foam: hundreds of groups whose windows each cover a
    large share of the detector), all
    their bubbles are fitted at once instead, on the whole detector, with the
    rest still held fixed: one fit whose evaluations project only those
    bubbles, instead of one fit per group over mostly the same pixels.

    Parameters
    ----------
    projector : MeshProjector
        Of ``data`` (local: windows are cut from its geometry).
    surfaces : list of SubdivisionSurface
    data : ndarray, ``projector.geometry.shape``
    changed : iterable of int
        Indices of the bubbles that changed.
    iterations : int
        BFGS iterations of each group's fit (of the joint fit), at most.
    touch : float
        Bubbles within this distance (mm) of a changed one are refitted with it.
    near : sequence of (centre, radius)
        See :func:`touching_groups`.
    residual : ndarray float64, optional
        ``Proj(surfaces) - data`` if known (updated in place); else computed with one projection.
    penalty : callable, optional
        Added to each group's objective (:func:`bubsub.clients.optimise.fit.fit`).
    progress : bool
        A progress bar over the groups, named ``label``.
    rtol : float, optional
        Each fit's convergence test (:func:`bubsub.clients.optimise.fit.fit`; default :data:`LOCAL_RTOL`);
        None runs ``iterations``.

    Returns
    -------
    surfaces : list of SubdivisionSurface
    residual : ndarray float64
        ``Proj(surfaces) - data`` of the returned bubbles.
    summary : dict
        ``groups``, ``bubbles`` (refitted, counted once per group), ``evaluations``, ``pixels`` (window
        pixels summed over the groups' fits), ``scan_pixels``, ``joint`` (whether the groups were fitted
        at once on the whole detector).
    """
    surfaces = list(surfaces)
    groups = touching_groups(surfaces, changed, touch, near=near)
    if residual is None:
        residual = scene_residual(projector, surfaces, data)
    scan_pixels = int(np.prod(projector.geometry.shape))
    summary = {"groups": len(groups), "bubbles": 0, "evaluations": 0, "pixels": 0, "scan_pixels": scan_pixels,
               "joint": False}
    if len(groups) > 1 and sum(Window(projector, [surfaces[k] for k in g]).pixels for g in groups) > scan_pixels:
        summary["joint"] = True
        _refit_joint(projector, surfaces, sorted({k for g in groups for k in g}), residual, iterations, penalty,
                     summary, progress=progress, label=label, rtol=rtol)
        return surfaces, residual, summary

    with phase(label, len(groups), unit="group", enabled=progress and bool(groups)) as bar:
        for group in groups:
            # its window from the bubbles as they are now: a bubble of two groups may have moved in the first
            _refit_group(projector, surfaces, group, Window(projector, [surfaces[k] for k in group]), residual,
                         iterations, penalty, summary, rtol=rtol)
            bar.update(1)
    return surfaces, residual, summary


def _refit_group(projector, surfaces, group, window, residual, iterations, penalty, summary, *, rtol=LOCAL_RTOL):
    """One group of :func:`local_refit` on its ``window``, in place on ``surfaces``, ``residual`` and ``summary``."""
    items = [surfaces[k] for k in group]
    old = [window.footprint(s) for s in items]
    part = np.ascontiguousarray(window.cut(others_removed(residual, *old)))
    res = fit(window.projector, items, part, iterations=iterations, progress=False, catch_interrupt=False,
              penalty=penalty, rtol=rtol)
    for k, s, o in zip(group, res.surfaces, old):
        o.add_to(residual, -1.0)
        footprint(projector, s).add_to(residual)  # it may have moved out of the group's window
        surfaces[k] = s
    summary["bubbles"] += len(group)
    summary["evaluations"] += res.evaluations
    summary["pixels"] += int(part.size) * res.evaluations


def _refit_joint(projector, surfaces, members, residual, iterations, penalty, summary, *, progress, label,
                 rtol=LOCAL_RTOL):
    """All ``members`` of :func:`local_refit`'s groups fitted at once on the whole detector, the others fixed."""
    items = [surfaces[k] for k in members]
    target = projector.forward(items).astype(np.float64)
    target -= residual  # the data minus every other bubble: the members' own projection minus the residual
    # L-BFGS whatever the count: the groups' union can reach dense BFGS's 6000 unknowns, whose inverse Hessian
    # (288 MB, and as much again while it is made) would set the peak memory of a large column's run
    res = fit(projector, items, target, iterations=iterations, progress=progress, catch_interrupt=False,
              penalty=penalty, label=label, method="lbfgs", rtol=rtol)
    for k, s in zip(members, res.surfaces):
        surfaces[k] = s
    np.subtract(projector.forward(res.surfaces), target, out=residual)
    summary["bubbles"] += len(members)
    summary["evaluations"] += res.evaluations
    summary["pixels"] += summary["scan_pixels"] * res.evaluations
