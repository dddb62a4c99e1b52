"""WPSE on real corrections: the ICT face, Live Link frames, the deformation-gradient blend."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax._metrics import CM_TO_MM
from canrig_jax.papers.wpse import NumpyEditEvaluator, reference_vertex_frames, retained_fraction
from canrig_jax.rig import evaluate
from canrig_jax.wpse import (
    apply,
    blendshape_metric,
    fit_prepared,
    fit_sigma,
    fit_width,
    prepare_edits,
)
from canrig_jax.wpse._frames import frame_matrices, local_frames


@pytest.fixture(scope="module")
def real_models(ict_face, real_edits):
    models = {}
    for name, metric in (("pse", "euclidean"), ("wpse", "weighted")):
        data = prepare_edits(
            ict_face, real_edits["poses"], real_edits["edits"], metric=metric, support_tol=1e-4
        )
        models[name] = fit_prepared(data, fit_sigma(data).sigma)
    return models


def mean_error_mm(meshes, desired):
    return float(np.linalg.norm(meshes - desired, axis=-1).mean() * CM_TO_MM)


@pytest.mark.slow
def test_frames_are_orthonormal_on_the_whole_face(ict_face):
    frames = local_frames(ict_face.faces, np.arange(ict_face.n_vertices), ict_face.n_vertices)
    rotation = np.asarray(frame_matrices(frames, evaluate(ict_face, jnp.full(53, 0.3))))
    assert np.all(np.isfinite(rotation))
    np.testing.assert_allclose(
        rotation @ np.swapaxes(rotation, 1, 2),
        np.broadcast_to(np.eye(3), rotation.shape),
        atol=1e-4,
    )


def test_frames_match_numpy_on_the_whole_face_with_the_jaw_open(ict_face):
    """The degree-grouped run-time frames against the plain NumPy accumulation of every
    triangle normal (float64), at every vertex of the face, jaw open."""
    vertices = np.arange(ict_face.n_vertices)
    frames = local_frames(ict_face.faces, vertices, ict_face.n_vertices)
    w = np.zeros(53, np.float32)
    w[list(ict_face.names).index("jawOpen")] = 1.0
    posed = np.asarray(evaluate(ict_face, w))
    got = np.asarray(jax.jit(frame_matrices)(frames, posed))
    expected = reference_vertex_frames(
        posed, ict_face.faces, vertices, np.asarray(frames.neighbour)
    )
    error = np.abs(got - expected)
    assert np.median(error) < 1e-6 and error.max() < 1e-5, (np.median(error), error.max())


@pytest.fixture(scope="module")
def real_meshes(real_models, real_edits):
    """{method: (meshes at the edit poses, meshes at the held-out frames)}: jit(vmap(apply))
    once per model, over the edit and held-out frames together (one compiled program each)."""
    run = jax.jit(jax.vmap(apply, (None, 0, 0)))
    poses = np.concatenate([real_edits["poses"], real_edits["test_poses"]])
    linear = np.concatenate([real_edits["linear"], real_edits["test_linear"]])
    n = len(real_edits["poses"])
    out = {}
    for name, model in real_models.items():
        meshes = np.asarray(run(model, poses, linear))
        out[name] = (meshes[:n], meshes[n:])
    return out


def test_run_time_matches_the_numpy_evaluator(real_models, real_edits, real_meshes):
    """jit(vmap(apply)) with local frames against ``NumpyEditEvaluator`` (padded incident
    rings, the straightforward layout) on real held-out frames."""
    for name, model in real_models.items():
        reference = NumpyEditEvaluator(model)
        held_out = real_meshes[name][1]
        for w, base, got in zip(
            real_edits["test_poses"][:4], real_edits["test_linear"][:4], held_out[:4], strict=True
        ):
            np.testing.assert_allclose(got, reference(w, base), atol=2e-5)


@pytest.mark.parametrize("method", ["pse", "wpse"])
def test_edits_reproduced_and_held_out_frames_improved(method, real_edits, real_meshes):
    at_edits, held_out = real_meshes[method]
    assert mean_error_mm(at_edits, real_edits["linear"] + real_edits["edits"]) < 0.01
    before = mean_error_mm(real_edits["test_linear"], real_edits["test_desired"])
    after = mean_error_mm(held_out, real_edits["test_desired"])
    assert after < 0.9 * before, (before, after)


@pytest.mark.slow
def test_locality_wpse_keeps_the_mouth_correction_pse_loses_it(ict_face, real_edits, real_models):
    """Seol et al. Fig. 7: the edited pose with different eye weights keeps its mouth fix."""
    names = ict_face.names
    eye = [i for i, n in enumerate(names) if n.startswith("eye")]
    mouth = [i for i, n in enumerate(names) if n.startswith(("mouth", "jaw"))]
    region = np.flatnonzero(blendshape_metric(ict_face.deltas)[:, mouth].sum(axis=1) > 0.5)
    rng = np.random.default_rng(0)
    kept = {"pse": [], "wpse": []}
    for pose, base in zip(real_edits["poses"][:4], real_edits["linear"][:4], strict=True):
        probe = pose.copy()
        probe[eye] = rng.uniform(0, 1, len(eye))
        probe_base = evaluate(ict_face, probe)
        for method, model in real_models.items():
            at_edit = apply(model, pose, base) - base
            at_probe = apply(model, probe, probe_base) - probe_base
            kept[method].append(retained_fraction(at_edit, at_probe, region))
    assert np.mean(kept["wpse"]) > 0.8, kept
    assert np.mean(kept["pse"]) < 0.5, kept


@pytest.mark.parametrize(
    "n_edits", [pytest.param(3, marks=pytest.mark.slow), 5, pytest.param(8, marks=pytest.mark.slow)]
)
def test_one_se_width_never_worse_than_the_rig_with_few_edits(n_edits, ict_face, real_edits):
    """Issue 24: with few real edits the width chosen by ``fit_width`` from the edits alone
    leaves the held-out frames better than the uncorrected rig."""
    data = prepare_edits(
        ict_face, real_edits["poses"][:n_edits], real_edits["edits"][:n_edits], support_tol=1e-4
    )
    model = fit_prepared(data, fit_width(data).sigma)
    run = jax.jit(jax.vmap(apply, (None, 0, 0)))
    held_out = np.asarray(run(model, real_edits["test_poses"], real_edits["test_linear"]))
    before = mean_error_mm(real_edits["test_linear"], real_edits["test_desired"])
    after = mean_error_mm(held_out, real_edits["test_desired"])
    assert after < before, (before, after)
