"""Every path of the compiled projection and analysis kernels, once, as a script for a subprocess.

:data:`RASTER_PATHS` is run with bounds checks by ``test_raster_bounds.py``; :func:`warm_up_command`
runs it with :data:`OTHER_PATHS` first in the test session's background lane (``conftest.py``), so
that the kernels are compiled into numba's disk cache on the second core while the first tests run (a
test that reaches a kernel first compiles it itself, as it would without the warm-up).
"""

import os
import sys
import textwrap

#: The raster backend's kernels: 2D and 3D, parallel and cone, sub-rays, the crossing store kept, filling
#: part-way and off, item by item.
RASTER_PATHS = textwrap.dedent("""
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

#: The native (Embree) backend's kernels on the same scenes, and the analysis kernels (shape moments,
#: one more Loop step, contacts) on two nearly touching spheres.
OTHER_PATHS = textwrap.dedent("""
    for geometry in (cone, par):
        P = MeshProjector(geometry, threads=2, backend="native")
        data = P.forward(items) * np.float32(0.9)
        P.objective(items, data)
        P.vjp(items, data)
    from bubsub.core.analysis.snapshot import analyse_meshes
    spheres = [sphere_surface([0.0, 0.0, 0.0], 0.3, 0.4).fine(), sphere_surface([0.62, 0.0, 0.0], 0.3, 0.4).fine()]
    analyse_meshes(spheres, contact_gap=0.05)
""")


def warm_up_command(tmp):
    """``(args, env, cwd)`` of the warm-up (see the module docstring), for ``conftest.BackgroundRun``."""
    return [sys.executable, "-c", "import os\n" + RASTER_PATHS + OTHER_PATHS], dict(os.environ), None
