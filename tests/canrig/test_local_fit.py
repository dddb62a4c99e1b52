"""The rig with no network (``LocalFitRig``) bound to the real ICT face by ``NeuralRig``: its
shape against an independent NumPy computation (per-patch ridge solves, the layout blend,
the gate of the largest clamped mask per vertex), the exact zeros (zero displacements,
vertices outside every clamped mask), the fitted pose A to B against a dense NumPy
least-squares solve, the workflows' guarantees on it, and bad input."""

import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.canrig import (
    FitOptions,
    NeuralRig,
    clip_edit,
    dialogue_replacement,
    iterative_layers,
    pose_a_to_b,
)
from canrig_jax.pbs import local_fit_rig, patch_layout, pbs_basis
from canrig_jax.rig import evaluate_batch, random_sparse_poses

N_PATCHES, N_HANDLES, RADIUS, FALLOFF, RIDGE = 60, 24, 2.0, 3.0, 1e-3


@pytest.fixture(scope="module")
def setup(ict_face):
    neutral = np.asarray(ict_face.neutral, np.float32)
    faces = np.asarray(ict_face.faces)
    layout = patch_layout(neutral, faces, N_PATCHES, rings=2)
    poses = random_sparse_poses(np.random.default_rng(11), 30, ict_face.names)
    shapes = np.asarray(evaluate_batch(ict_face, poses), np.float32)
    basis, _ = pbs_basis(neutral, shapes[:24], 8)
    rig = NeuralRig(local_fit_rig(layout, basis, ridge=RIDGE), neutral, faces)
    index = np.random.default_rng(12).choice(len(neutral), N_HANDLES, replace=False)
    return rig, layout, basis, shapes, rig.handles(index)


def _numpy_shape(rig, layout, basis, base, handles, d):
    """base + g * W_layout X(d) S_basis in float64: one ridge solve per patch, the gate
    g = min(1, 2 x the largest clamped mask)."""
    distance = np.asarray(handles.distance, np.float64)  # (V, H)
    with np.errstate(invalid="ignore"):
        mask = np.where(
            np.isfinite(distance), 0.5 * (1 - np.tanh(FALLOFF * (distance - RADIUS))), 0.0
        )
    mask = np.where(mask < rig.model.clamp, 0.0, mask)
    seeds = np.asarray(layout.seeds)
    a = basis[:, handles.index].astype(np.float64)  # (B-1, H, 3)
    scale = RIDGE * np.mean(a**2) * 3
    weights = np.stack(
        [
            np.linalg.solve(
                np.einsum("h,bhk,chk->bc", m, a, a) + scale * np.eye(len(a)),
                np.einsum("h,bhk,hk->b", m, a, d),
            )
            for m in mask[seeds]
        ]
    )  # (P, B-1)
    per_vertex = np.asarray(layout.matrix() @ weights)  # (V, B-1)
    gate = np.minimum(1.0, 2.0 * mask.max(axis=1))
    return base + gate[:, None] * np.einsum("vb,bvk->vk", per_vertex, basis), gate


def test_shape_is_gated_per_patch_ridge_solves_and_keeps_the_exact_zeros(setup):
    rig, layout, basis, shapes, handles = setup
    base, target = shapes[24], shapes[25]
    d = target[handles.index] - base[handles.index]
    ours = np.asarray(rig(handles, d, RADIUS, FALLOFF, base=base))
    expected, gate = _numpy_shape(rig, layout, basis, base, handles, d)
    np.testing.assert_allclose(ours, expected, rtol=1e-3, atol=2e-4)
    assert np.array_equal(np.asarray(rig(handles, 0 * d, RADIUS, FALLOFF, base=base)), base)
    outside = gate == 0
    assert 0 < outside.sum() < len(base)
    assert np.array_equal(ours[outside], base[outside])  # outside every clamped mask: exact
    assert np.abs(ours[~outside] - base[~outside]).max() > 1e-2  # and the edit does move


@pytest.mark.slow
def test_fitted_a_to_b_is_the_least_squares_solution_and_never_worse(setup):
    """Enough LSMR steps reach the dense minimiser of the region-weighted ||S(d) - B||^2
    (its Jacobian built column by column from the rig, solved by NumPy); the default three
    steps are never worse than the direct or zero displacements by the reported error."""
    rig, _, _, shapes, handles = setup
    a, b = shapes[26], shapes[27]
    region = np.random.default_rng(3).uniform(0.0, 2.0, rig.n_vertices).astype(np.float32)
    many = pose_a_to_b(
        rig, handles, a, b, RADIUS, FALLOFF, fit=True, region=region,
        options=FitOptions(max_steps=300),
    )  # fmt: skip
    columns = np.stack(
        [
            np.asarray(rig(handles, e.reshape(-1, 3), RADIUS, FALLOFF, base=a)) - a
            for e in np.eye(3 * N_HANDLES, dtype=np.float32)
        ],
        axis=-1,
    ).reshape(-1, 3 * N_HANDLES)
    root = np.repeat(np.sqrt(region), 3)[:, None]
    best, *_ = np.linalg.lstsq(root * columns, root[:, 0] * (b - a).ravel(), rcond=None)

    def objective(shape):
        return float(np.sum(region[:, None] * (np.asarray(shape) - b) ** 2))

    assert objective(many.shape) <= objective(a + (columns @ best).reshape(-1, 3)) * (1 + 1e-3)
    direct = pose_a_to_b(rig, handles, a, b, RADIUS, FALLOFF, region=region)
    np.testing.assert_array_equal(np.asarray(direct.displacements), (b - a)[handles.index])
    few = pose_a_to_b(rig, handles, a, b, RADIUS, FALLOFF, fit=True, region=region)
    assert int(few.steps) == FitOptions().max_steps
    assert float(few.error) <= min(float(few.direct_error), float(few.base_error))
    assert float(few.direct_error) == pytest.approx(float(direct.error), rel=1e-5)
    assert float(few.error) < float(direct.error)  # the fit does improve on this pair


@pytest.mark.slow
def test_workflows_keep_their_exact_guarantees(setup):
    """Layers: the fitted error never increases; clip edit: frames outside the window are
    bit-identical, vertices outside every mask do not move; dialogue: frame by frame the
    vmapped replacement equals one edit per frame."""
    rig, _, _, shapes, handles = setup
    a, b = shapes[26], shapes[27]
    rng = np.random.default_rng(5)
    schedule = [(rig.handles(rng.choice(rig.n_vertices, n, replace=False)), r) for n, r in
                ((6, 4.0), (20, 2.0), (40, 1.0))]  # fmt: skip
    layers = iterative_layers(rig, a, b, schedule, FALLOFF, fit=True)
    assert np.all(np.diff(layers.errors) <= 0) and layers.errors[-1] < layers.errors[0]

    clip = shapes[20:30]
    d = (b - a)[handles.index]
    edited = clip_edit(rig, clip, 5, handles, d, RADIUS, FALLOFF, 2)
    assert np.array_equal(edited.clip[:3], clip[:3]) and np.array_equal(edited.clip[8:], clip[8:])
    _, gate = _numpy_shape(rig, *setup[1:3], a, handles, d)
    assert np.array_equal(edited.clip[:, gate == 0], clip[:, gate == 0])
    assert np.abs(edited.clip[5] - clip[5]).max() > 1e-2

    source, target = shapes[20:23], shapes[23:26]
    out = dialogue_replacement(rig, source, target, handles, RADIUS, FALLOFF)
    for f in range(3):
        one = rig(handles, (target[f] - source[f])[handles.index], RADIUS, FALLOFF, base=source[f])
        # frames batched and one frame alone are different float32 programs (the patch
        # systems' elementwise Cholesky fuses differently): equal to 1 micrometre
        np.testing.assert_allclose(out[f], np.asarray(one), atol=1e-4)
    # fitted (vmapped LSMR) in a region: per frame never worse there than the direct pass
    region = gate > 0.5
    fitted = dialogue_replacement(
        rig, source, target, handles, RADIUS, FALLOFF, fit=True, region=region
    )

    def region_error(clip):
        return np.linalg.norm(clip - target, axis=-1)[:, region].mean(axis=1)

    assert np.all(region_error(fitted) <= region_error(out) + 1e-6)
    assert region_error(fitted).mean() < region_error(out).mean()
    assert np.array_equal(fitted[:, gate == 0], source[:, gate == 0])


def test_bad_input(setup, ict_face):
    rig, layout, basis, shapes, handles = setup
    with pytest.raises(ValueError, match="ridge"):
        local_fit_rig(layout, basis, ridge=0.0)
    with pytest.raises(ValueError, match="basis"):
        local_fit_rig(layout, basis[:, :100])
    with pytest.raises(ValueError, match="basis"):
        local_fit_rig(layout, np.concatenate([basis, basis[:1] * 2]))
    neutral = np.asarray(ict_face.neutral, np.float32)
    with pytest.raises(ValueError, match="canonical"):
        NeuralRig(rig.model, neutral[:-1], np.asarray(ict_face.faces)[:10])
    d = np.zeros((N_HANDLES, 3), np.float32)
    for kwargs, name in (({"radius": 0.0}, "radius"), ({"falloff": np.inf}, "falloff")):
        with pytest.raises(ValueError, match=name):
            rig(handles, d, **{"radius": RADIUS, "falloff": FALLOFF, **kwargs})
    with pytest.raises(ValueError, match="displacements"):
        rig(handles, d[:3], RADIUS, FALLOFF)
    with pytest.raises(ValueError, match="target"):
        pose_a_to_b(rig, handles, shapes[0], np.full_like(shapes[1], np.nan), RADIUS, FALLOFF)
    assert jnp.all(jnp.isfinite(rig(handles, d, RADIUS, FALLOFF)))
