"""The 2D-supervision experiment (issue 25) end to end in --quick mode (slow: minutes)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[3] / "experiments" / "autorig_2d.py"


def _run(argv: list[str]) -> None:
    """Run the experiment as its command line (a full experiment: slow tests only)."""
    subprocess.run([sys.executable, str(SCRIPT), *argv], check=True, cwd=SCRIPT.parents[1])


@pytest.mark.slow
def test_quick_experiment_writes_the_issue_keys(tmp_path):
    _run(["--quick", "--no-progress", "--out", str(tmp_path)])
    results = json.loads((tmp_path / "results.json").read_text())
    rasteriser = results["rasteriser"]
    assert rasteriser["grad_rel_error"] < 0.02
    assert rasteriser["hard_vs_reference_iou"] > 0.99
    assert rasteriser["fps_256"] > 0
    for run in ("3d_only", "2d_unrigged_plus_3d"):
        entry = results["training"][run]
        assert 0 < entry["ict_unseen_mae_mm"] < entry["ict_unseen_q95_mm"]
        assert entry["makehuman_mae_mm"] > 0
        assert entry["steps"] == 4  # same steps for both
    # the unrigged heads are not among the rigged ones
    setup = results["training_setup"]
    assert not set(setup["rigged_heads"]) & set(setup["unrigged_heads"])
    for name in ("rig_poses.png", "displacement_field.png", "training_loss.png", "table.md"):
        assert (tmp_path / name).stat().st_size > 0
