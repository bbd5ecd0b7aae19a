"""report.json and the summary line describe the bubbles written, also when the refined fit delivered them.

The truth is recomputed from the written files: the control polygons of control.json, subdivided, must give
bubbles.json's polygons, and their projections the reported objective on the fitted projections. The scan is
the quick dense 2D foam of ``python -m bubsub.bench bubbles dense2d --quick`` (Voronoi cells projected by
their pixel image, not by the fitted subdivision curves), whose films the 9-point polygons cannot follow,
so the refinement (9 -> 18 control points) is kept.
"""

import json

import numpy as np
import pytest

from bubsub.clients.cli.reconstruct import summary_line
from bubsub.clients.experiments.runner import EXPERIMENTS, case_config, simulate_case
from bubsub.clients.pipeline.results.outputs import write_outputs
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, load_initial, reconstruct
from bubsub.core import MeshProjector


@pytest.fixture(scope="module")
def refined(tmp_path_factory):
    exp = EXPERIMENTS["dense2d"]
    cfg = case_config(exp, True)
    _, scan, _, _ = simulate_case(2, 0, 25, 1e4, cfg, True, dense=True)
    rec = reconstruct(scan, ReconstructionSettings(iterations=cfg["iterations"], progress=False))
    out = tmp_path_factory.mktemp("rec")
    write_outputs(out, rec)
    return scan, rec.report, out


def test_the_refined_fit_is_delivered_and_reported_as_such(refined):
    scan, r, out = refined
    ref = r["refinement"]
    assert ref["kept"], "the dense foam's refinement pays for its unknowns"
    assert r["delivered_fit"] == "refined fit"
    assert r["iterations"] == r["fit"]["iterations"] + ref["iterations"]
    assert r["stop_reason"] == ref["stop_reason"]
    # the first fit's own figures stay under their own name, and differ from the delivered ones
    assert r["fit"]["objective"] > r["final_objective"]
    written = json.loads((out / "report.json").read_text())
    assert written["final_objective"] == pytest.approx(r["final_objective"], rel=1e-12)


def test_the_reported_objective_and_control_points_are_the_written_bubbles(refined):
    scan, r, out = refined
    control = json.loads((out / "control.json").read_text())["bubbles"]
    counts = {}
    for b in control:
        counts[str(len(b["vertices"]))] = counts.get(str(len(b["vertices"])), 0) + 1
    assert counts == r["control_points"] == {"18": r["bubbles"]}  # 9 points doubled by the refinement
    assert r["subdivision_levels"] == {"1": r["bubbles"]}  # one level moved into the control polygons
    surfaces = load_initial(out / "control.json", scan.bubble_contrast, levels=1)
    fine = json.loads((out / "bubbles.json").read_text())["bubbles"]
    for s, f in zip(surfaces, fine):
        np.testing.assert_allclose(s.fine().vertices, f["vertices"], atol=1e-5)
    assert r["projections_used"] == scan.n_angles
    residual = MeshProjector(scan.geometry).forward(surfaces) - scan.bubble_data
    assert r["final_objective"] == pytest.approx(0.5 * float(np.vdot(residual, residual)), rel=1e-4)


def test_the_summary_line_gives_the_delivered_objective_and_both_fits(refined):
    _, r, _ = refined
    line = summary_line(r)
    assert f"-> {r['final_objective']:.4g}," in line
    assert f"{r['fit']['iterations']} + {r['refinement']['iterations']} iterations (refined fit: " in line
    assert f"{r['fit']['objective']:.4g}" not in line
    plain = dict(r, delivered_fit="fit", iterations=r["fit"]["iterations"], stop_reason="iteration limit")
    assert f"{r['fit']['iterations']} iterations (iteration limit)" in summary_line(plain)
