"""A realistic raw scan (drifting flats, dead/hot pixels, stripes, off-centre axis, container, phase
contrast, Poisson noise) through ``bubsub prepare`` and ``reconstruct``: every bubble is found."""

import json

import h5py
import numpy as np
import pytest

from bubsub.clients.pipeline.evaluation.evaluate import evaluate_dir
from bubsub.clients.pipeline.results.outputs import write_outputs
from bubsub.clients.pipeline.reconstruct import ReconstructionSettings, reconstruct
from bubsub.clients.pipeline.evaluation.simulation import simulate_raw_to_dir
from bubsub.core.io.scanfile import read_scan
from bubsub.core.prep import prepare, prepare_options

COLS = 160


@pytest.fixture(scope="module")
def raw_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("raw")
    simulate_raw_to_dir(out, seed=3, n_bubbles=4, n_angles=40, cols=COLS, pixel_size=9.6 / COLS, rows=2,
                        supersample=2, photons=2e4, axis_offset=5.3)
    return out


def test_raw_file_looks_like_a_beamline_scan(raw_dir):
    meta = json.loads((raw_dir / "phantom.json").read_text())
    with h5py.File(raw_dir / "raw.h5") as f:
        data, white, dark = (f[f"exchange/{k}"][()] for k in ("data", "data_white", "data_dark"))
        assert data.dtype == np.uint16 and data.shape == (40, 2, COLS)
        assert f["measurement/instrument/monochromator/energy"].attrs["units"] == "keV"
    before, after = white[:10].astype(float), white[10:].astype(float)
    live = (before.mean(0) > 1000) & (before.mean(0) < 50000)
    assert after.mean(0)[live].mean() < 0.9 * before.mean(0)[live].mean()  # the beam decays
    assert (white.min(0) == 0).any() and (dark.max(0) == 60000).any()  # dead and hot pixels
    assert meta["axis_column"] == pytest.approx(COLS / 2 - 0.5 + 5.3)
    assert 1000 < meta["delta_beta"] < 2000  # water at 16 keV


def test_prepare_and_reconstruct_find_every_bubble(raw_dir):
    report = prepare(raw_dir / "raw.h5", raw_dir / "scan.h5", prepare_options(roi="1:2,:"), progress=False)
    steps = {s["step"]: s for s in report["steps"]}
    assert steps["center"]["axis_column_raw"] == pytest.approx(COLS / 2 - 0.5 + 5.3, abs=0.5)
    assert steps["contrast"]["bubble_contrast_per_mm"] == pytest.approx(-0.1, abs=0.02)
    scan = read_scan(raw_dir / "scan.h5")
    assert scan.ndim == 2
    rec = reconstruct(scan, ReconstructionSettings(iterations=20, progress=False))
    write_outputs(raw_dir / "rec", rec, scan_path=raw_dir / "scan.h5")
    res = evaluate_dir(raw_dir / "rec", raw_dir)
    assert res["bubbles_reconstructed"] == res["bubbles_truth"] == 4
    assert res["ddi"] <= 0.05
    import csv

    with open(raw_dir / "rec" / "bubbles.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["truncated"] for r in rows] == ["0"] * 4  # all inside the field of view
