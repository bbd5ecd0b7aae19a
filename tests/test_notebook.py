"""The example notebook runs from top to bottom (local fit, remote fit, results, plots)."""

import re
import sys
import time
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOK = Path(__file__).resolve().parents[1] / "examples" / "bubsub_tour.ipynb"


def _text(nb):
    out = []
    for cell in nb.cells:
        for o in cell.get("outputs", []):
            out.append(o.get("text", "") or "".join(o.get("data", {}).get("text/plain", "")))
    return "\n".join(out)


def execute(folder):
    """Run the notebook in ``folder`` (its outputs go there) and save it there, executed, as ``executed.ipynb``."""
    nb = nbformat.read(NOTEBOOK, as_version=4)
    t0 = time.perf_counter()
    NotebookClient(nb, timeout=240, kernel_name="python3", resources={"metadata": {"path": str(folder)}}).execute()
    nb.metadata["bubsub_seconds"] = time.perf_counter() - t0
    nbformat.write(nb, Path(folder) / "executed.ipynb")


def _execute_run(tmp):
    return [sys.executable, __file__, str(tmp)], None, None


@pytest.mark.background(command=_execute_run)  # a kernel process of its own: it runs beside the other tests
def test_the_example_notebook_runs_and_its_results_hold(background):
    res = background.wait(300)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-4000:]
    nb = nbformat.read(background.tmp / "executed.ipynb", as_version=4)
    text = _text(nb)
    ddi = float(re.search(r"DDI against the truth: ([0-9.]+)", text).group(1))
    assert ddi < 0.05
    local, remote = map(float, re.search(r"local objective (\S+), remote (\S+)", text).groups())
    assert remote == pytest.approx(local, rel=1e-3)  # the same fit, projected elsewhere
    assert "equivalent_diameter_mm" in text and "BubSub fit:" in text
    assert any(o.get("output_type") == "display_data" and "image/png" in o["data"]
               for c in nb.cells for o in c.get("outputs", []))
    assert (background.tmp / "bubsub-tour" / "local" / "bubbles.csv").is_file()
    print(f"notebook executed in {nb.metadata['bubsub_seconds']:.1f} s")


if __name__ == "__main__":
    execute(sys.argv[1])
