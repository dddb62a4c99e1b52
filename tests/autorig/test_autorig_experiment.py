"""The RigAnyFace experiment end to end in --quick mode (slow: several minutes)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "autorig.py"


@pytest.mark.slow
def test_quick_experiment_writes_the_issue_keys(tmp_path):
    spec = importlib.util.spec_from_file_location("autorig_experiment", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.main(["--quick", "--no-progress", "--out", str(tmp_path)])
    results = json.loads((tmp_path / "results.json").read_text())
    for method in ("raf", "raf_no_global_encoder", "deformation_transfer"):
        for split in ("same_topology", "unseen_topology"):
            stats = results["test"][method][split]
            assert 0 < stats["mae_mm"] < stats["q95_mm"]
    assert set(results["penetration"]) >= {"raf", "raf_no_global_encoder"}
    assert all(0 <= v <= 1 for v in results["penetration"].values())
    assert results["rig_seconds"]["cold"] > results["rig_seconds"]["warm"] > 0
    assert results["parameters"]["raf"] > results["parameters"]["raf_no_global_encoder"]
    assert results["gltf"]["max_abs_difference_cm"] == 0.0 and results["gltf"]["names_equal"]
    for name in (
        "table.md",
        "COMMAND",
        "training_loss.png",
        "poses_unseen_topology.png",
        "rig.glb",
    ):
        assert (tmp_path / name).exists()
