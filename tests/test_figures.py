"""Pictures of a reconstruction: mesh cross-sections, orthogonal slices, 3D rendering, size histogram."""

import json

import numpy as np
import pytest

from bubsub.clients.pipeline.results.figures import mesh_section, write_mesh_view, write_overlay, write_size_histogram
from bubsub.clients.pipeline.results.outputs import write_outputs
from bubsub.clients.pipeline.reconstruct import Reconstruction
from bubsub.core import sphere_surface
from bubsub.core import sphere_mesh


def _pixels(path):
    from matplotlib.image import imread

    return imread(path)[..., :3]


def _has_colour(img, rgb, tol=0.03):
    return bool(np.any(np.all(np.abs(img - np.asarray(rgb)[:3]) < tol, axis=-1)))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_mesh_section_of_a_sphere_is_its_circle(axis):
    centre = np.array([0.5, -0.2, 0.3])
    m = sphere_mesh(tuple(centre), 1.0, -0.1, subdivisions=4)
    value = centre[axis] + 0.6
    segs = mesh_section(m, axis, value)
    keep = [a for a in range(3) if a != axis]
    r = np.linalg.norm(segs.reshape(-1, 2) - centre[keep], axis=1)
    assert len(segs) > 50
    np.testing.assert_allclose(r, np.sqrt(1 - 0.6**2), rtol=5e-3)  # the inscribed mesh is a little inside
    # the segments close into one loop of the circle's length
    length = np.linalg.norm(segs[:, 1] - segs[:, 0], axis=1).sum()
    assert length == pytest.approx(2 * np.pi * 0.8, rel=5e-3)
    assert len(mesh_section(m, axis, centre[axis] + 1.5)) == 0


def test_pictures_show_each_bubble_in_its_id_colour(tmp_path):
    import matplotlib

    bubbles = [sphere_mesh((-1.5, 0, 0), 0.8, -0.1, 2), sphere_mesh((1.2, 0.5, 0.2), 0.6, -0.1, 2)]
    image = np.zeros((20, 40, 40), np.float32)
    extent = (-3, 3, -3, 3, -1.5, 1.5)
    write_overlay(tmp_path / "o.png", image, extent, bubbles, ids=[0, 1])
    write_mesh_view(tmp_path / "m.png", bubbles, ids=[0, 1])
    tab20 = matplotlib.colormaps["tab20"]
    for name in ("o.png", "m.png"):
        img = _pixels(tmp_path / name)
        assert _has_colour(img, tab20(0)) and _has_colour(img, tab20(1)), name
    write_size_histogram(tmp_path / "s.png", [1.2, 1.6, 1.7], 3)
    assert _has_colour(_pixels(tmp_path / "s.png"), matplotlib.colors.to_rgb("tab:blue"))


def test_outputs_of_a_3d_reconstruction(tmp_path):
    surfaces = [sphere_surface((-1.0, 0.2, 0.0), 0.7, -0.1), sphere_surface((1.0, -0.3, 0.1), 0.5, -0.1)]
    report = {"dimension": 3, "bubbles": 2, "interrupted": False}
    rec = Reconstruction(surfaces, report, np.zeros((10, 24, 24), np.float32), (-2, 2, -2, 2, -1, 1))
    files = write_outputs(tmp_path, rec)
    for key in ("overlay", "sizes", "meshes"):
        assert files[key].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    written = json.loads((tmp_path / "report.json").read_text())["files"]
    assert written["meshes"] == "meshes.png" and written["table_columns"] == "bubbles.csv-metadata.json"
    manifest = json.loads((tmp_path / "bubsub-outputs.json").read_text())
    assert set(manifest["files"]) == {p.name for p in files.values()}


def test_pictures_leave_pyplot_alone(tmp_path):
    # a notebook's inline backend must survive bubsub writing its pictures: no module may import
    # pyplot or switch the backend (a fresh interpreter, so other tests' imports do not count)
    import subprocess
    import sys

    code = f"""
import sys, numpy as np
from pathlib import Path
from bubsub.core import sphere_mesh
from bubsub.clients.pipeline.results.figures import write_overlay, write_size_histogram, write_mesh_view
from bubsub.clients.pipeline.dynamic4d.outputs4d import plot_growth, plot_mse, time_column
out = Path({str(tmp_path)!r})
m = sphere_mesh((0, 0, 0), 1.0, 0.5, subdivisions=2)
write_overlay(out / "o.png", np.ones((8, 8, 8), np.float32), (-2, 2, -2, 2, -2, 2), [m])
write_size_histogram(out / "s.png", [1.0, 1.2], 3)
write_mesh_view(out / "m.png", [m])
col = time_column("s")
plot_growth(out / "g.png", [{{"bubble_id": 1, col: t, "equivalent_diameter_mm": 1 + t}} for t in (0.0, 0.1)], "s")
plot_mse(out / "e.png", [{{"subscan": 0, "holdout_mse": 1.0}}, {{"subscan": 1, "holdout_mse": 0.5}}])
assert "matplotlib.pyplot" not in sys.modules, "pyplot was imported"
print("ok")
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr[-2000:]
    assert all((tmp_path / n).stat().st_size > 1000 for n in ("o.png", "s.png", "m.png", "g.png", "e.png"))


def test_size_histogram_of_equal_sizes(tmp_path):
    # sizes differing in the last bit (a monodisperse foam) gave numpy no finite bins and stopped write_outputs
    d = [0.5, 0.5 + 1e-16, 0.5]
    write_size_histogram(tmp_path / "s.png", d, 3)
    assert (tmp_path / "s.png").stat().st_size > 1000
