"""A generated rig as a product: the timing protocol (two triangulations alternating, medians)
and the glTF round trip, with the network and the reload replaced by stand-ins where the
bookkeeping is what is tested."""

from __future__ import annotations

import types

import equinox as eqx
import numpy as np
import pytest

from canrig_jax.autorig import RigAnyFaceTrainOptions
from canrig_jax.autorig._data import PoseSet
from canrig_jax.autorig._train import make_model
from canrig_jax.data import ICTFaceModel
from canrig_jax.papers.riganyface import gltf_round_trip, rig_timing
from canrig_jax.rig import BlendshapeRig

MODULE = "canrig_jax.papers.riganyface._generation"
POSES = PoseSet(("browInnerUp", "eyeBlinkLeft", "jawOpen"), ((0,), (1,), (2,), (0, 2)))


def _model(residual: bool):
    """A RigAnyFace of the right type without initialising its weights."""
    options = RigAnyFaceTrainOptions(residual=residual)
    return eqx.filter_eval_shape(make_model, options, POSES.n_basis, 1.0)


def test_rig_timing_alternates_two_triangulations_and_takes_medians(monkeypatch):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=4)  # 2,562 vertices
    n = len(sphere.vertices)
    head = ICTFaceModel(
        neutral=(np.asarray(sphere.vertices) * 10).astype(np.float32),
        faces=np.asarray(sphere.faces, np.int32),
        deltas=np.zeros((1, n, 3), np.float32),
        names=("jawOpen",),
        part_names=("Face",),
        part_vertex_range=np.asarray([[0, n]], np.int32),
        component_labels=np.zeros(n, np.int32),
        landmarks=np.zeros(68, np.int32),
        vertex_ids=np.arange(n, dtype=np.int32),
    )
    seen, seconds = [], iter(range(100, 0, -1))

    def generate(model, poses, v, f):
        seen.append(len(v))
        total = float(next(seconds))
        return types.SimpleNamespace(
            seconds={"total": total, "operators": total / 2, "network": total / 4}
        )

    monkeypatch.setattr(f"{MODULE}.generate_rig", generate)
    timing = rig_timing(_model(False), POSES, head, repeats=5)
    cold, warm = seen[0], seen[1:]
    assert timing["vertices"] == cold and timing["warm_repeats"] == len(warm) == 5
    # two triangulations of similar size alternate (the decimated head last)
    other = warm[0]
    assert other != cold and abs(other - cold) < 0.05 * cold
    assert warm == [other, cold, other, cold, cold]
    assert timing["cold"] == 100 and timing["warm"] == np.median([99, 98, 97, 96, 95])
    assert timing["warm_operators"] == 97 / 2 and timing["warm_orientation"] == 0.0
    with pytest.raises(ValueError, match="repeats"):
        rig_timing(_model(False), POSES, head, repeats=0)


def test_gltf_round_trip_reports_the_largest_difference(tmp_path, monkeypatch):
    rng = np.random.default_rng(1)
    rig = BlendshapeRig(
        rng.normal(size=(4, 3)).astype(np.float32),
        rng.normal(size=(2, 4, 3)).astype(np.float32),
        (),
        ("jawOpen", "eyeBlinkLeft"),
        np.asarray([[0, 1, 2], [0, 2, 3]], np.int32),
    )
    exact = gltf_round_trip(rig, tmp_path / "rig.glb")
    assert exact == {
        "file": "rig.glb",
        "morph_targets": 2,
        "max_abs_difference_cm": 0.0,
        "names_equal": True,
        "faces_equal": True,
    }
    moved = BlendshapeRig(rig.neutral, rig.deltas.at[1, 2, 0].add(0.25), (), rig.names, rig.faces)
    monkeypatch.setattr(f"{MODULE}.load_gltf_rig", lambda path: moved)
    assert gltf_round_trip(rig, tmp_path / "again.glb")["max_abs_difference_cm"] == pytest.approx(
        0.25
    )
