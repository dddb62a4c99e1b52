"""The CANRig experiments end to end in --quick mode (slow: a few minutes on 2 cores)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, EXPERIMENTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_quick_train_and_eval_write_the_issue_keys(tmp_path):
    _load("canrig_train").main(["--quick", "--no-progress", "--out", str(tmp_path)])
    checkpoint = tmp_path / "checkpoint.eqx"
    assert checkpoint.exists() and (tmp_path / "train.json").exists()
    _load("canrig_eval").main(["--quick", "--checkpoint", str(checkpoint), "--out", str(tmp_path)])
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


def test_pbs_graph_options_name_parts_and_refuse_another_attachment(tmp_path):
    from types import SimpleNamespace

    import numpy as np

    pbs = _load("canrig_pbs")
    model = SimpleNamespace(
        part_names=["Face", "Teeth"], part_vertex_range=[(0, 3), (3, 5)], neutral=np.zeros((5, 3))
    )
    np.testing.assert_array_equal(
        pbs._part_mask(model, ["Teeth"], "--attach"), [False, False, False, True, True]
    )
    with pytest.raises(ValueError, match="--attach-onto: unknown ICT parts"):
        pbs._part_mask(model, ["Lips"], "--attach-onto")
    folder = tmp_path / "per_patch"
    folder.mkdir()
    meta = {"graph": "attached", "attach": ["Teeth"], "attach_onto": ["Face"]}
    (folder / "train.json").write_text(json.dumps(meta))
    args = pbs._parser().parse_args(["--out", str(tmp_path), "--graph", "attached"])
    with pytest.raises(ValueError, match="--attach: "):  # trained with Teeth only
        pbs._check_graph(args, folder)
    args.attach = ["Teeth"]
    pbs._check_graph(args, folder)  # the same attachment resumes
    with pytest.raises(ValueError, match="--graph: "):
        pbs._check_graph(pbs._parser().parse_args(["--out", str(tmp_path)]), folder)


@pytest.mark.slow
def test_pbs_quick_attached_graph_end_to_end(tmp_path):
    pbs = _load("canrig_pbs")
    argv = ["--quick", "--no-progress", "--out", str(tmp_path), "--graph", "attached"]
    pbs.main([*argv, "--train", "per_patch", "--steps", "20", "--decay-steps", "20"])
    meta = json.loads((tmp_path / "models" / "per_patch" / "train.json").read_text())
    assert meta["graph"] == "attached" and meta["attach_onto"] == ["Face"]
    pbs.main(argv)
    results = json.loads((tmp_path / "results.json").read_text())
    assert "per_patch" in results["table5"]
    reach = results["table5_reach"]["regions"]
    assert reach["face"]["within_reach"] == 1.0 and reach["mouth_interior"]["patches"] > 0
    assert reach["mouth_interior"]["within_reach"] > 0.9
    assert results["table6"]["methods"]["per_patch"]["rest_of_face_change_mm"] == 0.0
