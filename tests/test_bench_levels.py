"""bench levels: it starts where ``bubsub reconstruct``'s fit starts."""

import numpy as np


def test_the_levels_benchmark_starts_from_the_pipelines_initial_bubbles(tmp_path, monkeypatch):
    import bubsub.clients.pipeline.reconstruct as pipeline
    from bubsub.bench.levels import start
    from bubsub.clients.cli.main import main
    from bubsub.core.io.scanfile import read_scan

    assert main(["simulate", "--phantom", "column", "--bubbles", "25", "--det-count", "96", "--angles", "12",
                 "--out", str(tmp_path / "sim")]) == 0
    scan = read_scan(tmp_path / "sim" / "scan.h5")
    seen = {}

    class Started(Exception):
        pass

    def first_fit(projector, surfaces, data, **options):  # the pipeline's fit, reached: note where it starts
        seen["surfaces"] = surfaces
        raise Started

    monkeypatch.setattr(pipeline, "fit_levels", first_fit)
    try:
        pipeline.reconstruct(scan, pipeline.ReconstructionSettings(progress=False))
    except Started:
        pass
    ours = start(scan)
    assert len(ours) == len(seen["surfaces"]) > 5
    for a, b in zip(ours, seen["surfaces"]):
        assert a.levels == b.levels
        np.testing.assert_array_equal(a.vertices, b.vertices)
