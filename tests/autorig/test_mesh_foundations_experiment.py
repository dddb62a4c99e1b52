"""The mesh-foundations experiment end to end in --quick mode (slow: about a minute)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "mesh_foundations.py"


def _run(argv: list[str]) -> None:
    """Run the experiment as its command line (a full experiment: slow tests only)."""
    subprocess.run([sys.executable, str(SCRIPT), *argv], check=True, cwd=SCRIPT.parents[1])


@pytest.mark.slow
def test_quick_experiment_writes_the_issue_keys(tmp_path):
    _run(["--quick", "--out", str(tmp_path)])
    results = json.loads((tmp_path / "results.json").read_text())
    assert set(results["operator_seconds"]) == {"first", "cached"}
    assert results["operator_seconds"]["cached"] < 1.0 < results["operator_seconds"]["first"]
    assert results["n_zero_eigenvalues"] == results["n_components"] == 56
    assert results["spectral_vs_expm_max_error"] < 1e-4
    assert results["retriangulation_agreement"]["max"] < 0.01
    assert results["deformation_transfer_mae_mm"] < 0.5
    assert results["deformation_transfer_q95_mm"] < 2.0
    for name in ("table.md", "COMMAND", "deformation_transfer_error.png"):
        assert (tmp_path / name).exists()
    assert "--quick" in (tmp_path / "COMMAND").read_text()
