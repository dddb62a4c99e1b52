"""The RigAnyFace experiment end to end in --quick mode (slow: several minutes)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from canrig_jax._checkpoint import parameter_count
from canrig_jax.autorig import RigAnyFaceTrainOptions
from canrig_jax.autorig._train import make_model
from canrig_jax.papers.riganyface import FACE_PLACED

EXPERIMENTS = Path(__file__).resolve().parents[3] / "experiments"


def _run(argv: list[str], script: str = "autorig.py") -> None:
    """Run an experiment as its command line (a full experiment: slow tests only)."""
    path = EXPERIMENTS / script
    subprocess.run([sys.executable, str(path), *argv], check=True, cwd=EXPERIMENTS.parent)


@pytest.mark.slow
def test_quick_experiment_writes_the_issue_keys(tmp_path):
    _run(
        [
            *("--quick", "--no-progress", "--out", str(tmp_path), "--anchored-residual"),
            *("--anchor", "skin_vertex"),  # a second anchored base and its residual model
        ]
    )
    results = json.loads((tmp_path / "results.json").read_text())
    for method in ("raf", "raf_no_global_encoder", "deformation_transfer"):
        for split in ("same_topology", "unseen_topology"):
            stats = results["test"][method][split]
            assert 0 < stats["mae_mm"] < stats["q95_mm"]
    # issue 19's keys: held-out errors by pose class and vertex class, MakeHuman
    methods = {
        "no_motion",
        "copy_deltas",
        "deformation_transfer",
        "raf",
        "raf_no_global_encoder",
        "raf_dt_residual",
        # anchored deformation transfer, the residual model on it, and trained on it
        "deformation_transfer_anchored",
        "raf_dt_residual_anchored",
        "raf_anchored_dt_residual",
        # anchored per vertex on the skin and per part elsewhere, and its residual model
        "deformation_transfer_anchored_skin_vertex",
        "raf_anchored_skin_vertex_dt_residual",
    }
    assert set(results["heldout"]) == methods == set(results["makehuman"])
    for method, subsets in results["heldout"].items():
        assert set(subsets) == {"single", "combinations"}
        for s in subsets.values():
            assert {"mae_mm", "q95_mm", "static_mae_mm", "moving_mae_mm"} <= set(s)
            f = s["static_fraction"]
            assert abs(f * s["static_mae_mm"] + (1 - f) * s["moving_mae_mm"] - s["mae_mm"]) < 1e-6
        assert len(results["worst_poses"][method]) == 5
    assert results["heldout"]["no_motion"]["single"]["static_mae_mm"] < 0.01
    # anchored DT holds what the ICT pose leaves still: far less static error than plain DT
    anchored = results["heldout"]["deformation_transfer_anchored"]
    for subset in ("single", "combinations"):
        plain_static = results["heldout"]["deformation_transfer"][subset]["static_mae_mm"]
        assert anchored[subset]["static_mae_mm"] < 0.5 * plain_static
    assert results["training"]["raf_anchored_dt_residual"]["base"].endswith("_anchored")
    base = results["training"]["raf_anchored_skin_vertex_dt_residual"]["base"]
    assert base == "deformation_transfer_anchored_skin_vertex"
    # per part off the skin (whole parts held or free): the static pairs of a moving part
    # are not held, so more static error than per vertex, but less than plain DT
    per_part = results["heldout"]["deformation_transfer_anchored_skin_vertex"]
    for subset in ("single", "combinations"):
        plain_static = results["heldout"]["deformation_transfer"][subset]["static_mae_mm"]
        assert anchored[subset]["static_mae_mm"] <= per_part[subset]["static_mae_mm"]
        assert per_part[subset]["static_mae_mm"] < plain_static
    for e in results["makehuman"].values():
        assert set(e) == {"skin_mae_mm", "skin_q95_mm", "active_mae_mm", "amplitude_ratio_median"}
    assert results["makehuman"]["no_motion"]["amplitude_ratio_median"] == 0
    assert results["makehuman_protocol"]["shared_shapes"] == 51
    # the residual model starts at deformation transfer and trains 20 steps in quick mode
    dt, residual = results["heldout"]["deformation_transfer"], results["heldout"]["raf_dt_residual"]
    assert abs(residual["single"]["mae_mm"] / dt["single"]["mae_mm"] - 1) < 0.5
    assert set(results["penetration"]) >= {"raf", "raf_no_global_encoder"}
    assert all(0 <= v <= 1 for v in results["penetration"].values())
    assert results["rig_seconds"]["cold"] > results["rig_seconds"]["warm"] > 0
    assert results["parameters"]["raf"] > results["parameters"]["raf_no_global_encoder"]
    assert results["gltf"]["max_abs_difference_cm"] == 0.0 and results["gltf"]["names_equal"]
    # the claims the results are for (paper: topology-agnostic; quick mode trains 20 steps,
    # so accuracy itself is not claimed here, only what does not depend on training length)
    test = results["test"]
    for method in ("raf", "raf_no_global_encoder"):
        same, unseen = test[method]["same_topology"], test[method]["unseen_topology"]
        assert abs(unseen["mae_mm"] / same["mae_mm"] - 1.0) < 0.15  # any triangulation alike
    # penetration of the inner parts as in the ground truth rigs (no new intersections)
    truth = results["penetration"]["ground_truth"]
    assert abs(results["penetration"]["raf"] - truth) < 0.01
    # the deformation-transfer baseline is sub-millimetre on held-out ICT identities
    assert test["deformation_transfer"]["same_topology"]["mae_mm"] < 1.0
    assert test["deformation_transfer"]["unseen_topology"]["mae_mm"] < 1.0
    assert results["provenance"]["command"].startswith("python experiments/autorig.py")
    for name in (
        "table.md",
        "COMMAND",
        "training_loss.png",
        "poses_unseen_topology.png",
        "rig.glb",
        "makehuman.png",
        "makehuman_shapes.png",
    ):
        assert (tmp_path / name).exists()


@pytest.mark.slow
def test_wider_model_trained_alone_then_evaluated_on_heldout_and_makehuman(tmp_path):
    """``--raf-width`` / ``--raf-conditional-blocks`` size the pure model (autorig_train.py);
    autorig_evaluate.py evaluates a checkpoint trained outside the standard folder on the
    held-out identities and the MakeHuman head, next to the baselines, training nothing."""
    sizes = {}
    for width in (16, 24):
        out = tmp_path / f"w{width}"
        _run(
            [
                *("raf", "--quick", "--no-progress", "--out", str(out)),
                *("--raf-width", str(width), "--raf-conditional-blocks", "3"),
            ],
            "autorig_train.py",
        )
        assert not (out / "results.json").exists()  # training alone writes no results
        sizes[width] = out / "checkpoint_raf.eqx"
    _run(
        [
            *("--no-progress", "--out", str(tmp_path / "eval"), "--test-identities", "1"),
            *(str(sizes[16]), str(sizes[24])),
        ],
        "autorig_evaluate.py",
    )
    results = json.loads((tmp_path / "eval" / "results.json").read_text())
    rows = ("w16/checkpoint_raf", "w24/checkpoint_raf")
    # validation (how models are chosen): class errors and the per-shape record, which shows
    # whether the upper face moves; deformation transfer moves it
    _run(
        [
            *("--no-progress", "--out", str(tmp_path / "val"), "--validation-identities", "1"),
            *(str(sizes[16]), str(sizes[24])),
        ],
        "autorig_validate.py",
    )
    checked = json.loads((tmp_path / "val" / "validation.json").read_text())
    assert set(checked["validation"]) >= {"no_motion", "deformation_transfer", *rows}
    val_shapes = checked["validation_shapes"]
    assert set(val_shapes["methods"]) == set(checked["validation"]) - {"no_motion"}
    dt_peak = np.asarray(val_shapes["methods"]["deformation_transfer"]["peak_ratio"])
    assert np.median(dt_peak[np.asarray(val_shapes["upper_face"])]) > 0.5
    assert set(results["heldout"]) == {
        "no_motion",
        "copy_deltas",
        "deformation_transfer",
        "deformation_transfer_anchored",
        *rows,
    }
    # MakeHuman: the same rows, and each model once more placed from its fitted face
    face_rows = {name + FACE_PLACED for name in rows}
    assert set(results["makehuman"]) == set(results["heldout"]) | face_rows
    for name in rows:
        options = results["training"][name]["options"]
        assert options["n_conditional"] == 3 and results["training"][name]["steps"] == 20
    assert [results["training"][r]["options"]["width"] for r in rows] == [16, 24]
    # the checkpoints hold models of the requested size
    for name in rows:
        options = RigAnyFaceTrainOptions(**results["training"][name]["options"])
        expected = parameter_count(make_model(options, 53, 1.0))
        assert results["parameters"][name] == expected
    assert results["parameters"][rows[0]] < results["parameters"][rows[1]]
    # the baselines reproduce the standard evaluation's definitions
    assert results["heldout"]["no_motion"]["single"]["static_mae_mm"] < 0.01
    assert results["makehuman"]["no_motion"]["amplitude_ratio_median"] == 0
    for subsets in results["heldout"].values():
        for s in subsets.values():
            f = s["static_fraction"]
            assert abs(f * s["static_mae_mm"] + (1 - f) * s["moving_mae_mm"] - s["mae_mm"]) < 1e-6
    # penetration where the ground truth has none: zero for the truth and no motion
    clean = results["penetration_clean"]
    assert set(clean) == set(results["heldout"]) | {"ground_truth"}
    assert clean["ground_truth"]["fraction"] == clean["no_motion"]["fraction"] == 0
    for c in clean.values():
        assert 0 <= c["fraction"] <= 1 and 0 <= c["poses_with_any"] <= 1
        assert (c["fraction"] > 0) == (c["poses_with_any"] > 0)
    # the per-shape MakeHuman record recombines to the summary (same shapes, same skin)
    shapes = results["makehuman_shapes"]
    assert set(shapes["methods"]) == set(results["makehuman"]) - {"no_motion"}
    for name, e in shapes["methods"].items():
        summary = results["makehuman"][name]
        assert np.median(e["amplitude_ratio"]) == pytest.approx(summary["amplitude_ratio_median"])
        assert np.mean(e["skin_mae_mm"]) == pytest.approx(summary["skin_mae_mm"], rel=1e-6)
    assert any(shapes["upper_face"]) and not all(shapes["upper_face"])
    # per single expression on the held-out heads: copying the ICT deltas (0.05 mm MAE) moves
    # every shape by its true amount; the rows are the held-out ones but no motion
    held = results["heldout_shapes"]
    assert set(held["methods"]) == set(results["heldout"]) - {"no_motion"}
    assert len(held["labels"]) == len(held["upper_face"]) == 53 and 0 < sum(held["upper_face"]) < 53
    copied = np.asarray(held["methods"]["copy_deltas"]["peak_ratio"])
    assert 0.8 < np.median(copied) < 1.25
    for name in (
        "table.md",
        "training_loss.png",
        "poses_unseen_topology.png",
        "makehuman.png",
        "makehuman_shapes.png",
        "heldout_shapes.png",
    ):
        assert (tmp_path / "eval" / name).exists()
