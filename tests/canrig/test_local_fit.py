"""The rig with no network (``LocalFitRig``) on the real ICT face: its shape against an
independent NumPy computation (per-patch ridge solves, then the layout blend), the exact
zeros (zero displacements, vertices no reached patch covers), the fitted pose A to B against
a dense NumPy least-squares solve, and bad input."""

import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.canrig import (
    edge_graph,
    local_fit_a_to_b,
    local_fit_rig,
    local_fit_shape,
    patch_layout,
    pbs_basis,
    seed_distances,
)
from canrig_jax.rig import evaluate_batch, random_sparse_poses

N_PATCHES, N_HANDLES, RADIUS, FALLOFF = 60, 24, 2.0, 3.0


@pytest.fixture(scope="module")
def setup(ict_face):
    neutral = np.asarray(ict_face.neutral, np.float32)
    faces = np.asarray(ict_face.faces)
    layout = patch_layout(neutral, faces, N_PATCHES, rings=2)
    poses = random_sparse_poses(np.random.default_rng(11), 30, ict_face.names)
    shapes = np.asarray(evaluate_batch(ict_face, poses), np.float32)
    basis, _ = pbs_basis(neutral, shapes[:24], 8)
    handles = np.random.default_rng(12).choice(len(neutral), N_HANDLES, replace=False)
    distance = seed_distances(layout, edge_graph(neutral, faces))[:, handles]
    rig = local_fit_rig(layout, basis, ridge=1e-3)
    return rig, layout, basis, shapes, handles, distance.astype(np.float32)


def _numpy_shape(layout, basis, base, handles, distance, d, ridge, clamp):
    mask = 0.5 * (1 - np.tanh(FALLOFF * (distance - RADIUS)))
    mask = np.where(mask < clamp, 0.0, mask)
    a = basis[:, handles].astype(np.float64)  # (B-1, H, 3)
    scale = ridge * np.mean(a**2) * 3
    weights = np.stack(
        [
            np.linalg.solve(
                np.einsum("h,bhk,chk->bc", m, a, a) + scale * np.eye(len(a)),
                np.einsum("h,bhk,hk->b", m, a, d),
            )
            for m in mask
        ]
    )  # (P, B-1)
    per_vertex = np.asarray(layout.matrix() @ weights)  # (V, B-1)
    return base + np.einsum("vb,bvk->vk", per_vertex, basis), mask


def test_shape_is_per_patch_ridge_solves_blended_and_keeps_the_exact_zeros(setup):
    rig, layout, basis, shapes, handles, distance = setup
    base, target = shapes[24], shapes[25]
    d = target[handles] - base[handles]
    ours = np.asarray(local_fit_shape(rig, base, handles, distance, d, RADIUS, FALLOFF))
    expected, mask = _numpy_shape(layout, basis, base, handles, distance, d, 1e-3, rig.clamp)
    np.testing.assert_allclose(ours, expected, rtol=1e-3, atol=2e-4)
    zero = local_fit_shape(rig, base, handles, distance, 0 * d, RADIUS, FALLOFF)
    assert np.array_equal(np.asarray(zero), base)
    batch = local_fit_shape(rig, base, handles, distance, np.stack([d, 0 * d]), RADIUS, FALLOFF)
    np.testing.assert_allclose(np.asarray(batch[0]), ours, atol=1e-5)  # a batch: vmapped
    assert np.array_equal(np.asarray(batch[1]), base)
    reached = (mask > 0).any(axis=1)
    assert 0 < reached.sum() < N_PATCHES
    covered = np.asarray(layout.matrix()[:, reached].sum(axis=1)).ravel() > 0
    assert np.array_equal(ours[~covered], base[~covered])
    assert np.abs(ours[covered] - base[covered]).max() > 1e-2  # and the edit does move


def test_fitted_a_to_b_is_the_least_squares_solution_and_never_worse(setup):
    """Enough LSMR steps reach the dense least-squares minimiser of ||S(d) - B||^2 (its
    Jacobian built column by column from S, solved by NumPy); a few steps never do worse
    than the direct displacements."""
    rig, _, _, shapes, handles, distance = setup
    a, b = jnp.asarray(shapes[26]), jnp.asarray(shapes[27])
    args = (rig, a, b, handles, distance, RADIUS, FALLOFF)
    direct, d0 = local_fit_a_to_b(*args, 0)
    fitted, d = local_fit_a_to_b(*args, 300)
    columns = np.stack(
        [
            np.asarray(
                local_fit_shape(rig, a, handles, distance, e.reshape(-1, 3), RADIUS, FALLOFF)
            )
            - np.asarray(a)
            for e in np.eye(3 * N_HANDLES, dtype=np.float32)
        ],
        axis=-1,
    ).reshape(-1, 3 * N_HANDLES)
    best, *_ = np.linalg.lstsq(columns, (np.asarray(b) - np.asarray(a)).ravel(), rcond=None)
    best_error = np.linalg.norm(columns @ best - (np.asarray(b) - np.asarray(a)).ravel())
    ours_error = np.linalg.norm(np.asarray(fitted - b))
    assert ours_error <= best_error * (1 + 1e-3)
    direct_error = np.linalg.norm(np.asarray(direct - b))
    assert ours_error < direct_error
    np.testing.assert_array_equal(np.asarray(d0), np.asarray(b - a)[handles])

    def mean_error(shape):
        return np.linalg.norm(np.asarray(shape - b), axis=-1).mean()

    for steps in (1, 3):  # the reported error (mean distance), never worse than direct or zero
        few, _ = local_fit_a_to_b(*args, steps)
        assert mean_error(few) <= min(mean_error(direct), mean_error(a))


def test_bad_input(setup):
    rig, layout, basis, shapes, handles, distance = setup
    a, b = shapes[0], shapes[1]
    good = (rig, a, b, handles, distance, RADIUS, FALLOFF)
    for position, bad, name in (
        (1, a[:10], "a"),
        (2, np.where(np.arange(len(b))[:, None] == 3, np.nan, b), "b"),
        (3, np.concatenate([handles[:-1], handles[:1]]), "handle_index"),
        (3, handles.astype(np.float32), "handle_index"),
        (4, distance[:, :5], "seed_distance"),
        (4, -distance, "seed_distance"),
        (5, 0.0, "radius"),
        (6, np.inf, "falloff"),
    ):
        args = list(good)
        args[position] = bad
        with pytest.raises(ValueError, match=name):
            local_fit_a_to_b(*args)
    with pytest.raises(ValueError, match="max_steps"):
        local_fit_a_to_b(*good, -1)
    d = np.zeros((len(handles), 3), np.float32)
    with pytest.raises(ValueError, match="displacements"):
        local_fit_shape(rig, a, handles, distance, d[:3], RADIUS, FALLOFF)
    with pytest.raises(ValueError, match="base"):
        local_fit_shape(rig, a[:, :2], handles, distance, d, RADIUS, FALLOFF)
    with pytest.raises(ValueError, match="ridge"):
        local_fit_rig(layout, basis, ridge=0.0)
    with pytest.raises(ValueError, match="basis"):
        local_fit_rig(layout, basis[:, :100])
    with pytest.raises(ValueError, match="basis"):
        local_fit_rig(layout, np.concatenate([basis, basis[:1] * 2]))
