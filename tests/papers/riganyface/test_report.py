"""The RigAnyFace experiments' report: ``autorig_table`` rebuilds every committed ``table.md``
from its ``results.json`` (the standard run's layout and that of checkpoints evaluated
apart), so the tables in the repository say what the numbers next to them say."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from canrig_jax.papers.riganyface import autorig_table

RESULTS = Path(__file__).resolve().parents[3] / "experiments" / "results"
FOLDERS = sorted(
    p.name
    for p in RESULTS.glob("autorig*")
    if (p / "results.json").is_file()
    and (p / "table.md").is_file()
    and p.name not in ("autorig_2d", "autorig_robust")  # their own tables
)


def test_the_committed_folders_cover_both_layouts():
    layouts = {"test" in json.loads((RESULTS / f / "results.json").read_text()) for f in FOLDERS}
    assert layouts == {True, False} and len(FOLDERS) >= 10


@pytest.mark.parametrize("folder", FOLDERS)
def test_table_is_the_committed_one(folder):
    results = json.loads((RESULTS / folder / "results.json").read_text())
    assert autorig_table(results) == (RESULTS / folder / "table.md").read_text()


def test_table_shows_each_row_with_its_values():
    """A row added to the results appears in its tables with its numbers, rounded as shown."""
    results = json.loads((RESULTS / "autorig_long" / "results.json").read_text())
    row = dict(next(iter(results["heldout"].values())))
    row["single"] = {**row["single"], "mae_mm": 1.23456}
    results["heldout"]["new_model"] = row
    results["makehuman"]["new_model"] = {
        "skin_mae_mm": 0.5,
        "skin_q95_mm": 2.0,
        "active_mae_mm": 3.0,
        "amplitude_ratio_median": 0.25,
    }
    text = autorig_table(results)
    assert "| new_model | 1.235 |" in text
    assert "| new_model | 0.500 | 2.00 | 3.00 | 0.25 |" in text
    with pytest.raises(KeyError):
        autorig_table({k: v for k, v in results.items() if k != "heldout_protocol"})
