"""The CANRig experiments end to end in --quick mode (slow: a few minutes on 2 cores)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.papers.canrig import check_pbs_training_matches, reach_floor
from canrig_jax.pbs import PatchLayout

ROOT = Path(__file__).resolve().parents[3]


def _run(name: str, argv: list[str]) -> None:
    """Run ``experiments/<name>.py`` as its command line (a full experiment: slow tests only)."""
    script = ROOT / "experiments" / f"{name}.py"
    subprocess.run([sys.executable, str(script), *argv], check=True, cwd=ROOT)


@pytest.mark.slow
def test_quick_train_and_eval_write_the_issue_keys(tmp_path):
    _run("canrig_train", ["--quick", "--no-progress", "--out", str(tmp_path)])
    checkpoint = tmp_path / "checkpoint.eqx"
    assert checkpoint.exists() and (tmp_path / "train.json").exists()
    _run("canrig_eval", ["--quick", "--checkpoint", str(checkpoint), "--out", str(tmp_path)])
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["zero_preservation_max_mm"] == 0.0
    assert results["outside_region_change_max_mm"] == 0.0
    assert set(results["handles_radius_mm"]) == {"20", "75", "200"}
    for by_radius in results["handles_radius_mm"].values():
        assert set(by_radius) == {"small", "medium", "large"}
    assert len(results["layers_mm"]) == 3
    for key in ("forward_ms", "train_minutes", "parameters"):
        assert results[key] > 0
    assert results["blocked_vs_dense_max_mm"] < 1e-3
    for name in ("table.md", "mask_radii.png", "heldout_error.png", "training_loss.png"):
        assert (tmp_path / name).exists()


def test_pbs_graph_option_refuses_another_attachment(tmp_path):
    # (the --attach / --attach-onto part names: ICTFaceModel.part_mask, tests/data/test_ict.py)
    folder = tmp_path / "per_patch"
    folder.mkdir()
    check_pbs_training_matches(folder, handles_on="moving", graph="mesh")  # nothing recorded
    meta = {"graph": "attached", "attach": ["Teeth"], "attach_onto": ["Face"]}
    (folder / "train.json").write_text(json.dumps(meta))
    run = {"handles_on": "skin", "graph": "attached", "attach_onto": ["Face"]}
    with pytest.raises(ValueError, match="--attach: "):  # trained with Teeth only
        check_pbs_training_matches(folder, **run, attach=["Teeth", "Gums and tongue"])
    check_pbs_training_matches(folder, **run, attach=("Teeth",))  # the same attachment resumes
    with pytest.raises(ValueError, match="--graph: "):
        check_pbs_training_matches(folder, handles_on="skin", graph="bridged")
    with pytest.raises(ValueError, match="--handles-on: "):  # before the option: the skin
        check_pbs_training_matches(
            folder, handles_on="moving", graph="attached", attach=["Teeth"], attach_onto=["Face"]
        )
    # the Shape Transformer has no masks: only where its handles are drawn is checked
    transformer = tmp_path / "shape_transformer"
    transformer.mkdir()
    (transformer / "train.json").write_text(json.dumps({"handles_on": "moving"}))
    check_pbs_training_matches(transformer, handles_on="moving", graph="bridged")
    with pytest.raises(ValueError, match="--handles-on: "):
        check_pbs_training_matches(transformer, handles_on="skin", graph="bridged")


@pytest.mark.slow
def test_pbs_quick_attached_graph_end_to_end(tmp_path):
    argv = ["--quick", "--no-progress", "--out", str(tmp_path), "--graph", "attached"]
    _run(
        "canrig_pbs_train", [*argv, "--model", "per_patch", "--steps", "20", "--decay-steps", "20"]
    )
    meta = json.loads((tmp_path / "models" / "per_patch" / "train.json").read_text())
    assert meta["graph"] == "attached" and meta["attach_onto"] == ["Face"]
    _run("canrig_pbs", argv)
    results = json.loads((tmp_path / "results.json").read_text())
    assert "per_patch" in results["table5"]
    reach = results["table5_reach"]["regions"]
    assert reach["face"]["within_reach"] == 1.0 and reach["mouth_interior"]["patches"] > 0
    assert reach["mouth_interior"]["within_reach"] > 0.9
    assert results["table6"]["per_patch"]["rest_of_face_change_mm"] == 0.0
    assert results["table6_setup"]["mouth_handles"] >= 1
    # the handle sweep: no network goes below the reach floor, more handles never raise it,
    # the exact zero outside the region holds for every count; re-running replaces the section
    for _ in range(2):
        _run("canrig_pbs_table6_sweep", [*argv, "--counts", "2", "8"])
    sweep = json.loads((tmp_path / "results.json").read_text())["table6_handle_sweep"]
    rows = sweep["mouth_difference_mm"]
    assert rows["2"]["reach_floor_mm"] >= rows["8"]["reach_floor_mm"]
    for row in rows.values():
        assert row["per_patch"] >= row["reach_floor_mm"] - 1e-6
        assert row["per_patch_rest_of_face_change_max_mm"] == 0.0
    header = "Table 6, a variant: the number of mouth handles"  # the sweep's section
    assert (tmp_path / "table.md").read_text().count(header) == 1
    assert "table5" in json.loads((tmp_path / "results.json").read_text())  # kept


def test_reach_floor_counts_only_vertices_no_moved_handle_reaches():
    """Two patches over four vertices; the handle reaches patch 0 only: vertices covered by
    patch 1 alone keep the source, and their error averaged over the region is the floor."""
    layout = PatchLayout(
        vertex_patches=jnp.array([[0, 0], [0, 1], [1, 1], [1, 1]]),
        vertex_weights=jnp.array([[1.0, 0.0], [0.5, 0.5], [1.0, 0.0], [1.0, 0.0]]),
        seeds=jnp.array([0, 2]),
        cell=jnp.array([0, 0, 1, 1]),
    )
    distances = np.array([[0.0, 0.0, 0.0, 0.0], [99.0, 99.0, 99.0, 99.0]])  # (P, N)
    source = np.zeros((1, 4, 3), np.float32)
    target = np.zeros((1, 4, 3), np.float32)
    target[0, :, 0] = [0.1, 0.2, 0.3, 0.4]  # cm
    region = np.array([True, True, True, False])
    handles = np.array([0])
    floor, unreached = reach_floor(layout, distances, handles, source, target, region, reach_cm=1.0)
    assert unreached == 1  # vertex 2 (vertex 1 is also covered by the reached patch 0)
    assert floor == pytest.approx(3.0 / 3)  # 3 mm at vertex 2, averaged over 3 region vertices
    # a reach beyond patch 1's seed reaches every vertex: no floor
    assert reach_floor(layout, distances, handles, source, target, region, reach_cm=100.0) == (0, 0)
    with pytest.raises(ValueError, match="reach_cm"):
        reach_floor(layout, distances, handles, source, target, region, reach_cm=0.0)
    with pytest.raises(ValueError, match="patch_distance_cm"):
        reach_floor(layout, distances[:1], handles, source, target, region, reach_cm=1.0)
