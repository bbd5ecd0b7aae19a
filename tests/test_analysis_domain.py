"""The analysed domain of ``bubsub analyse`` is the sample: liquid fractions count no air around it."""

import json

import numpy as np
import pytest

from bubsub.clients.analysis.domain import parse_domain
from bubsub.clients.cli.main import main
from bubsub.clients.pipeline.results.outputs import write_outputs
from bubsub.clients.pipeline.reconstruct import Reconstruction
from bubsub.core.analysis.regions import Domain
from bubsub.core.projection.subdivision import sphere_surface
from test_analysis_cli import C, FOV, rows

BALLS = [((-0.5, 0.0, 0.0), 0.45), ((0.5, 0.1, 0.0), 0.4), ((0.0, -0.7, 0.2), 0.35)]
BOX = (2.4, 2.4, 1.6)  # the liquid box of the simulated sample, centred at the origin


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A reconstruct folder whose report names a simulated scan with its phantom.json (a liquid box)."""
    root = tmp_path_factory.mktemp("sample")
    sim, rec = root / "sim", root / "rec"
    sim.mkdir()
    (sim / "scan.h5").write_bytes(b"")  # only its folder is read
    (sim / "phantom.json").write_text(json.dumps({"phantom": "foam3d", "ndim": 3, "size": list(BOX)}))
    surfaces = [sphere_surface(c, r, C, levels=3) for c, r in BALLS]
    write_outputs(rec, Reconstruction(surfaces, {"dimension": 3, "field_of_view_mm": FOV}, ids=[1, 2, 3]),
                  scan_path=sim / "scan.h5")
    return rec


def gas():
    return sum(4 / 3 * np.pi * r ** 3 for _, r in BALLS)


def test_the_liquid_fraction_is_the_simulated_samples(simulated, tmp_path, capsys):
    out = tmp_path / "an"
    assert main(["analyse", str(simulated), "--out", str(out), "--quiet", "--no-pictures"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    # the analytic balls in the liquid box, not in the field of view's cylinder (that would be 0.981)
    assert summary["liquid_fraction"] == pytest.approx(1 - gas() / np.prod(BOX), abs=1e-3)
    domain = summary["domain"]
    assert domain["kind"] == "box" and domain["hi_mm"] == pytest.approx(np.array(BOX) / 2)
    assert "phantom.json" in domain["source"]
    assert sum(float(r["region_volume_mm3"]) for r in rows(out / "regions_grid.csv")) == pytest.approx(
        np.prod(BOX), rel=2e-3)
    assert "in the box of the simulated sample" in capsys.readouterr().out


def test_a_domain_asked_for_is_cut_to_the_field_of_view(simulated, tmp_path):
    out = tmp_path / "an"
    assert main(["analyse", str(simulated), "--out", str(out), "--quiet", "--no-pictures",
                 "--domain", "box:-3,3,-3,3,-1,1"]) == 0
    domain = json.loads((out / "summary.json").read_text())["domain"]
    assert domain["kind"] == "cylinder" and domain["radius_mm"] == 2.4 and domain["source"].startswith("asked")
    shells = rows(out / "regions_shells.csv")
    assert sum(float(r["region_volume_mm3"]) for r in shells) == pytest.approx(np.pi * 2.4 ** 2 * 2.0, rel=2e-3)
    assert main(["analyse", str(simulated), "--out", str(out), "--quiet", "--no-pictures", "--overwrite",
                 "--domain", "fov"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["liquid_fraction"] == pytest.approx(1 - gas() / (np.pi * 2.4 ** 2 * 2.4), abs=1e-3)


@pytest.mark.parametrize("spec, words", [("ball:1", "is not one of"), ("box:1,2,3", "is not one of"),
                                         ("box:1,0,0,1,0,1", "lower bound below"),
                                         ("box:5,6,5,6,0,1", "do not overlap")])
def test_a_bad_domain_is_refused_in_one_line(simulated, tmp_path, capsys, spec, words):
    assert main(["analyse", str(simulated), "--out", str(tmp_path / "an"), "--domain", spec]) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and len(err.splitlines()) == 1 and not (tmp_path / "an").exists()


def test_domains_intersect_into_a_box_a_cylinder_or_a_box_within_a_cylinder():
    fov = Domain.field_of_view(2.0, 1.0)
    assert Domain.box((-1, 1, -1, 1, -2, 2)).intersect(fov) == Domain((-1, -1, -1), (1, 1, 1), None)
    cut = Domain.box((-1.8, 1.8, -1, 1, 0, 2)).intersect(fov)
    assert cut.kind == "box within cylinder" and cut.radius == 2.0 and cut.lo == (-1.8, -1, 0)
    # both in the box, the first outside the cylinder
    assert cut.contains([[1.79, 0.99, 0.5], [1.7, 0.9, 0.5]]).tolist() == [False, True]
    assert parse_domain("cylinder:1.5", (2.0, 1.0)) == Domain((-1.5, -1.5, -1), (1.5, 1.5, 1), 1.5)
    assert parse_domain("Sample") == "sample"


def _scan_of(tmp_path, name, container, size):
    """A cone-beam scan (no bubbles) whose background is the exact projection of a container mesh."""
    from bubsub.core.foam.simulate import default_geometry_3d
    from bubsub.core.io.scanfile import Scan, write_scan
    from bubsub.core.projection.projector import MeshProjector

    g = default_geometry_3d(16, rows=32, cols=48, source_origin=40.0, origin_detector=20.0, size=size)
    background = MeshProjector(g).forward([container])
    return write_scan(tmp_path / f"{name}.h5", Scan(data=background, geometry=g, background=background,
                                                      bubble_contrast=-0.1))


def test_the_sample_is_fitted_to_the_scans_background(tmp_path):
    """A box and a cylinder, projected by the mesh projector, are told apart and measured from the background."""
    import trimesh

    from bubsub.clients.analysis.domain import analysed_domain, background_sample
    from bubsub.core.foam.containers import liquid_box
    from bubsub.core.projection.mesh import Mesh

    box_scan = _scan_of(tmp_path, "box", liquid_box((3.0, 2.4, 1.6), 0.1), (3.0, 2.4, 1.6))
    box, residual = background_sample(box_scan)
    assert box.kind == "box" and residual < 1e-3
    assert box.lo + box.hi == pytest.approx((-1.5, -1.2, -0.8, 1.5, 1.2, 0.8), abs=0.01)
    tube = trimesh.creation.cylinder(radius=1.2, height=1.6, sections=256)
    cyl_scan = _scan_of(tmp_path, "cyl", Mesh(tube.vertices, tube.faces, 0.1), (2.4, 2.4, 1.6))
    cyl, residual = background_sample(cyl_scan)
    assert cyl.kind == "cylinder" and residual < 0.01
    assert cyl.radius == pytest.approx(1.2, abs=0.01) and (cyl.lo[2], cyl.hi[2]) == pytest.approx((-0.8, 0.8), abs=0.01)
    # a reconstruction of that scan without a phantom.json takes it, and says so
    domain, source = analysed_domain(None, {"scan": str(cyl_scan)}, tmp_path, (3.0, 1.0))
    assert domain.kind == "cylinder" and "background" in source and domain.hi[2] == pytest.approx(0.8, abs=0.01)


def test_an_unreadable_scan_leaves_the_field_of_view(tmp_path):
    from bubsub.clients.analysis.domain import analysed_domain

    (tmp_path / "scan.h5").write_text("not HDF5")
    domain, source = analysed_domain("sample", {"scan": str(tmp_path / "scan.h5")}, tmp_path, (2.0, 1.0))
    assert domain == Domain.field_of_view(2.0, 1.0) and "the sample is not known: pass --domain" in source
