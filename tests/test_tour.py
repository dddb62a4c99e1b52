"""examples/tour.ipynb runs top to bottom on the real data (nbclient; -m slow)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

NOTEBOOK = Path(__file__).resolve().parents[1] / "examples" / "tour.ipynb"


@pytest.mark.slow
def test_tour_notebook_executes(tmp_path, monkeypatch):
    nbclient = pytest.importorskip("nbclient", reason="pip install nbclient ipykernel (dev)")
    nbformat = pytest.importorskip("nbformat")
    monkeypatch.setenv("TOUR_OUT", str(tmp_path))
    notebook = nbformat.read(NOTEBOOK, as_version=4)
    client = nbclient.NotebookClient(
        notebook,
        timeout=1200,
        kernel_name="python3",
        resources={"metadata": {"path": str(NOTEBOOK.parent)}},
    )
    client.execute()  # raises CellExecutionError naming the cell on any error
    text = "".join(
        o.get("text", "")
        for cell in notebook.cells
        if cell.cell_type == "code"
        for o in cell.get("outputs", [])
    )
    figures = sorted(p.name for p in tmp_path.glob("*.png"))
    assert figures == [
        "capture_weights.png",
        "inverse_jaw_open.png",
        "makehuman_jaw_open.png",
        "wpse_error.png",
    ]
    assert (tmp_path / "take.csv").is_file() and (tmp_path / "makehuman_anim.glb").is_file()
    # the claims the tour prints: the inverse rig recovers the take, WPSE moves unseen frames
    # towards the sculpt, the MakeHuman head's unit is inferred
    mesh = re.search(r"mesh: mean ([\d.]+) mm", text)
    assert mesh and float(mesh.group(1)) < 0.01, text
    wpse = re.search(r"([\d.]+) mm before, ([\d.]+) mm after WPSE", text)
    assert wpse and float(wpse.group(2)) < float(wpse.group(1)), text
    assert "units: dm (inferred)" in text
    if "Khronos validator" in text:
        assert "Khronos validator: 0 errors" in text
