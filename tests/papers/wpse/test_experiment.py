"""The WPSE experiment end to end in --quick mode, then its timing rows (slow: 5-8 minutes on
2 shared cores)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

EXPERIMENTS = Path(__file__).resolve().parents[3] / "experiments"


def _run(script: str, argv: list[str]) -> None:
    """Run a script as its command line (a full experiment: slow tests only)."""
    path = EXPERIMENTS / script
    subprocess.run([sys.executable, str(path), *argv], check=True, cwd=EXPERIMENTS.parent)


@pytest.mark.slow
def test_quick_experiment_writes_the_issue_keys(tmp_path):
    _run("wpse.py", ["--quick", "--out", str(tmp_path)])
    assert "timing" not in json.loads((tmp_path / "results.json").read_text())
    _run("wpse_timing.py", ["--out", str(tmp_path)])
    results = json.loads((tmp_path / "results.json").read_text())
    for method in ("linear", "pse", "wpse", "fsm", "quartic"):
        for budget in ("p10", "p50"):
            assert set(results["errors"][method][budget]) >= {"mean_mm", "p95_mm"}
    assert set(results["locality"]) >= {"pse_retained", "wpse_retained"}
    for row in results["timing"]:
        assert set(row) >= {"vertices", "edits", "train_s", "runtime_ms", "numpy_runtime_ms"}
    assert results["sigma"]
    for budget in ("5", "10", "20", "50"):
        for method in ("linear", "pse", "wpse", "wpse_new_width"):
            assert set(results["few_edits"][budget][method]) >= {"mean_mm", "p95_mm"}
    assert set(results["temporal"]) >= {"max_step_mm", "max_acceleration_mm", "take_max_step_mm"}
    assert set(results["reuse"]) >= {"error_before_mm", "error_after_mm", "tau"}
    # issue 24: the one-standard-error width never leaves the rig worse than uncorrected
    for row in results["few_edits"].values():
        assert row["wpse_new_width"]["mean_mm"] < row["linear"]["mean_mm"]
    for name in ("table.md", "error_maps.png", "overshoot.png", "search.png", "temporal.png"):
        assert (tmp_path / name).exists()
    # the claims that hold on real data (see the README for the ones that do not)
    errors = results["errors"]
    assert errors["wpse"]["p50"]["mean_mm"] < 0.8 * errors["linear"]["p50"]["mean_mm"]
    assert errors["wpse"]["p50"]["mean_mm"] < errors["fsm"]["p50"]["mean_mm"]
    assert results["locality"]["wpse_retained"] >= 0.8 > results["locality"]["pse_retained"]
