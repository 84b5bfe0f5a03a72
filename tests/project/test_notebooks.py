"""Both notebooks execute top to bottom on artefacts made in this test session."""

import os

import nbformat
import pytest
from nbclient import NotebookClient

from helpers.paths import ROOT

NOTEBOOKS = ROOT / "notebooks"


def _execute(name, tmp_path, **env):
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    old = {k: os.environ.get(k) for k in env}
    os.environ.update({k: str(v) for k, v in env.items()})  # the kernel inherits them
    try:
        NotebookClient(notebook, timeout=300, kernel_name="python3",
                       resources={"metadata": {"path": str(tmp_path)}}).execute()  # fmt: skip
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return notebook


def _text(notebook):
    return "\n".join(
        o.get("text", "")
        + str(o.get("data", {}).get("text/plain", ""))
        + str(o.get("data", {}).get("text/markdown", ""))
        for cell in notebook.cells if cell.cell_type == "code" for o in cell.outputs
    )  # fmt: skip


@pytest.mark.slow
def test_demo_notebook_shows_bb_lite_full_similarity_maps(tiny_export, tmp_path):
    notebook = _execute("demo.ipynb", tmp_path, RESIREG_EXPORT=tiny_export)
    text = _text(notebook)
    for name in ("BB (head only)", "ReSiReg Lite", "ReSiReg Full"):
        assert f"{name}:" in text
    # Lite and Full are twice as fine as the head's grid (upscale 2): 96 x 128 px, patch 16.
    assert "(6, 8) similarity" in text and "(12, 16) similarity" in text
    images = [
        o for c in notebook.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})
    ]
    assert images, "the figure was not drawn"


@pytest.mark.slow
def test_sweep_analysis_notebook_shows_table_failures_and_heatmap(prototype_sweep, tmp_path):
    notebook = _execute("sweep_analysis.ipynb", tmp_path, RESIREG_SWEEP=prototype_sweep[0])
    text = _text(notebook)
    assert "6 jobs, 2 did not complete" in text
    assert "best prototype count per batch size" in text
    assert '"slope"' in text
