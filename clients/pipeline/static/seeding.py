"""The pipeline's seeds: its voxel preview and the initial bubbles in it, with the options of its settings.

:func:`~bubsub.clients.pipeline.reconstruct.reconstruct`'s first phases
(:func:`~bubsub.clients.pipeline.reconstruct.seed_phase`,
:func:`~bubsub.clients.pipeline.reconstruct.radius_phase`) run these; the
benchmarks that start where the pipeline starts (``bubsub bench levels``,
``bubsub bench detection``) call them with the same settings.
"""

from __future__ import annotations

from dataclasses import replace

from bubsub.core import MeshProjector, ScanGeometry

from bubsub.clients.optimise.fit import estimate_radii
from bubsub.clients.optimise.levels import coarse_surfaces
from bubsub.clients.pipeline.inputs.fov import preview_extension
from bubsub.clients.pipeline.static.initial import choose_initial, default_detector
from bubsub.clients.pipeline.static.preview import preview_voxel_size, voxel_for_bubbles, voxel_preview

__all__ = ["initial_bubbles", "settings_preview", "settings_initial", "coarse_radii", "coarse_radii_with",
           "finer_voxel"]


def initial_bubbles(data, geometry, contrast, projector, settings, *, clock=None):
    """The pipeline's initial bubbles from its voxel preview of ``data`` (bubbles positive).

    :func:`settings_preview` and :func:`settings_initial`, then, when the
    seeds are a few voxels across (:func:`voxel_for_bubbles`), both again on
    a finer preview.

    Parameters
    ----------
    data : ndarray, ``(angles, rows, cols)`` or ``(angles, cols)``
    geometry : ScanGeometry
        Of ``data``.
    contrast : float
    projector : MeshProjector
        Of ``data`` (local).
    settings : ReconstructionSettings
    clock : optional
        The pipeline's phase clock (``preview`` and ``initial_bubbles`` marked).

    Returns
    -------
    surfaces : list of SubdivisionSurface
    initialisation : dict
        :func:`choose_initial`'s summary.
    image : ndarray float32
        The preview the seeds come from; ``extent`` its grid (mm).
    extent : tuple
    finer : float or None
        The finer preview's voxel (mm) when one was made.
    """
    mark = clock.mark if clock is not None else (lambda name: None)
    image, extent = settings_preview(data, geometry, contrast, settings)
    mark("preview")
    surfaces, initialisation = settings_initial(image, extent, contrast, projector, data, settings)
    finer = finer_voxel(settings, surfaces, geometry, data, contrast)
    if finer is not None:  # bubbles a few voxels across: seeded again in a preview fine enough for them
        mark("initial_bubbles")
        image, extent = settings_preview(data, geometry, contrast, replace(settings, voxel_size=finer))
        mark("preview")
        surfaces, initialisation = settings_initial(image, extent, contrast, projector, data, settings)
    return surfaces, initialisation, image, extent, finer


def settings_preview(data, geometry, contrast, settings):
    """The pipeline's voxel preview of ``data`` (bubbles positive): ``(image, extent)``."""
    return voxel_preview(data, geometry, contrast, settings.voxel_size, progress=settings.progress,
                         method=settings.preview, extend=preview_extension(settings.fov_model, data, contrast))


def settings_initial(image, extent, contrast, projector, data, settings):
    """The pipeline's initial bubbles in the preview (:func:`choose_initial` with ``settings``'s options):
    ``(surfaces, summary)``. ``auto`` compares the candidate sets after their radius-only fits, here."""
    detector = default_detector(settings.detector, projector.geometry.ndim)
    return choose_initial(image, extent, contrast, projector, data, detector=detector,
                          estimate=settings.estimate_radii and detector == "auto", progress=settings.progress,
                          control_points=settings.control_points, levels=settings.levels, radius=settings.radius,
                          min_distance=settings.min_distance, border_is_background=not settings.fov_model)


def coarse_radii(surfaces, geometry, data, factor, settings):
    """The radius-only pre-fit (:func:`estimate_radii`) on the detector binned by ``factor`` (the fit's
    coarsest level: the radii need not see every pixel), at that level's subdivision
    (:func:`coarse_surfaces`, as the fit's binned level); the surfaces come back at their own."""
    return coarse_radii_with(surfaces, geometry, data, factor, supersampling=settings.supersampling,
                         progress=settings.progress)


def coarse_radii_with(surfaces, geometry, data, factor, *, supersampling=1, progress=False):
    """:func:`coarse_radii` with its options as keywords: rays per pixel and axis, progress line."""
    coarse = MeshProjector(geometry.binned(factor), supersampling=supersampling)
    levels = [x.levels for x in surfaces]
    return coarse_surfaces(estimate_radii(coarse, coarse_surfaces(surfaces, factor, levels),
                                          ScanGeometry.bin_projections(data, factor), progress=progress),
                           1, levels)


def finer_voxel(settings, surfaces, geometry, data, contrast):
    """:func:`voxel_for_bubbles` of ``surfaces`` (their equivalent radii) against the default preview
    voxel; None when the voxel size is asked for (``settings.voxel_size``) or the bubbles are wide enough
    in voxels."""
    if settings.voxel_size is not None or not surfaces:
        return None
    return voxel_for_bubbles([x.fine().equivalent_radius for x in surfaces], geometry, preview_voxel_size(geometry),
                             preview_extension(settings.fov_model, data, contrast))
