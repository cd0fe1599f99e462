"""The notebooks in `notebooks/` run top to bottom (in their quick mode, set by
NHJAX_NOTEBOOK_QUICK=1), so that they cannot rot; each ends with cells that assert what
its story claims. Their committed copies are executed, with outputs."""

import json
import pathlib

import matplotlib
import matplotlib.pyplot as plt
import pytest


NOTEBOOKS = sorted((pathlib.Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))


def _code_cells(path):
    return [cell for cell in json.loads(path.read_text())["cells"] if cell["cell_type"] == "code"]


def test_at_least_three_notebooks_are_committed_executed():
    assert len(NOTEBOOKS) >= 3
    for path in NOTEBOOKS:
        cells = _code_cells(path)
        assert all(cell["execution_count"] is not None for cell in cells), path.name
        outputs = [output for cell in cells for output in cell["outputs"]]
        assert not any(output["output_type"] == "error" for output in outputs), path.name
        assert any("image/png" in output.get("data", {}) for output in outputs), path.name


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda path: path.stem)
def test_notebook_runs_top_to_bottom(path, monkeypatch, tmp_path):
    monkeypatch.setenv("NHJAX_NOTEBOOK_QUICK", "1")
    monkeypatch.chdir(tmp_path)
    matplotlib.use("Agg")
    namespace = {"__name__": "__main__"}
    try:
        for index, cell in enumerate(_code_cells(path)):
            exec(compile("".join(cell["source"]), f"{path.name}, code cell {index}", "exec"), namespace)
    finally:
        plt.close("all")
