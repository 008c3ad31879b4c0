"""Execute every notebook in notebooks/ at small size (JAXPLUSH_SMALL=1), as CI must.

Notebooks run with notebooks/ as their working directory and write any files to a temporary
directory, never into the checkout.
"""

from __future__ import annotations

import pathlib

import pytest

#: notebooks that run only in the CI tier (`-m heavy`): each compiles many programs
HEAVY = ("speed_vs_error", "fit_material_parameters", "parameter_sweeps", "plush_pile", "fit_from_a_depth_camera")
NOTEBOOKS = sorted((pathlib.Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", [pytest.param(p, marks=pytest.mark.heavy) if p.stem in HEAVY else p for p in NOTEBOOKS],
                         ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes(path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("JAXPLUSH_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(path.parent)}})
    client.execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_committed_notebooks_show_their_outputs(path):
    """A reader sees a notebook's results without running it: it is committed executed (every
    code cell ran, in order, without an error; `python notebooks/execute.py` saves them so), with
    at least one plot."""
    import json
    nb = json.loads(path.read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code" and "".join(c["source"]).strip()]
    counts = [c.get("execution_count") for c in code]
    assert all(isinstance(n, int) for n in counts), f"{path.name}: cells not executed: {counts}"
    assert counts == sorted(counts), f"{path.name}: cells executed out of order: {counts}"
    outputs = [o for c in code for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"], f"{path.name} was saved with an error"
    assert any("image/png" in o.get("data", {}) for o in outputs), f"{path.name} shows no plot"
