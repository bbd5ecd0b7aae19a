"""The raster backend's kernels index arrays without bounds checks (numba's default): one write past
an array's end corrupts the heap silently and crashes a later, unrelated test. This runs every
kernel path once in a subprocess compiled with ``NUMBA_BOUNDSCHECK=1``, where such an access
raises IndexError instead."""

import os
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent("""
    import numpy as np
    from bubsub.core import Mesh, MeshProjector, ScanGeometry, sphere_surface, circle_surface
    from bubsub.core.projection.backends import raster

    angles = np.linspace(0, np.pi, 4, endpoint=False)
    cone = ScanGeometry.cone(angles, source_origin=30.0, origin_detector=5.0, pixel_size=0.1, cols=24, rows=16)
    par = ScanGeometry.parallel(angles, pixel_size=0.1, cols=24, rows=16)
    # a tetrahedron across the detector: every face is crossed in every projection, the case in
    # which the gradient pass's candidate listing reached one place past its last face
    tet = Mesh(np.array([[0.4, 0.0, -0.3], [-0.4, 0.35, -0.3], [-0.4, -0.35, -0.3], [0.0, 0.0, 0.4]]),
               np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]), 0.5)
    os.environ["BUBSUB_RASTER_STORE_MB"] = "0"
    full = []
    for geometry in (cone, par):  # the tetrahedron alone, its gradient rasterised again
        P = MeshProjector(geometry, threads=2, backend="raster")
        full.append((P.trace([tet])._job.hit[:, 0] == 15).any())
        P.vjp([tet], P.forward([tet]))
    assert any(full)  # all four faces crossed in some projection
    items = [tet, sphere_surface([0.2, 0.1, 0.0], 0.3, 0.4, levels=2), sphere_surface([-0.5, 0.3, 0.1], 0.2, 0.3)]
    for geometry in (cone, par):
        for sub in (1, 2):
            P = MeshProjector(geometry, threads=2, backend="raster", supersampling=sub)
            data = P.forward(items) * np.float32(0.9)
            for mb in ("", "0.0005", "0"):  # store kept, filling part-way, off (the gradient rasterises again)
                os.environ["BUBSUB_RASTER_STORE_MB"] = mb
                P.objective(items, data)
            P.vjp(items, data)
            default, raster.ITEM_MAJOR_FACES = raster.ITEM_MAJOR_FACES, 0  # item by item, the same scene
            P.objective(items, data)
            raster.ITEM_MAJOR_FACES = default
    P2 = MeshProjector(ScanGeometry.parallel(angles, pixel_size=0.1, cols=24), backend="raster")
    circles = [circle_surface([0.1, 0.0], 0.5, 0.4)]
    P2.objective(circles, P2.forward(circles))
    print("bounds ok")
""")


def bounds_checked_run(tmp):
    env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=str(tmp), BUBSUB_RASTER_STORE_MB="")
    return [sys.executable, "-c", "import os\n" + SCRIPT], env, None


@pytest.mark.background(command=bounds_checked_run)  # a compile of every kernel with bounds checks, beside the other tests
def test_raster_kernels_stay_in_bounds(background):
    res = background.wait(600)
    assert res.returncode == 0 and "bounds ok" in res.stdout, res.stdout[-2000:] + res.stderr[-4000:]
