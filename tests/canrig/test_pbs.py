"""Patch blendshapes (PBS, CANRig section 4) on the real ICT face: the layout (geodesic
Voronoi cells grown by rings, rows summing to 1), the basis, the per-patch fit, the gather
form against the sparse W_layout, and the global-blendshape baseline."""

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from canrig_jax.mesh import vertex_adjacency
from canrig_jax.pbs import PatchLayout, fit_pbs, local_pbs_fit, patch_layout, pbs_basis, pbs_shape
from canrig_jax.pbs._basis import (
    check_basis,
    global_blendshape_dialogue,
    global_blendshape_fit,
    local_fit_factor,
    local_fit_solve,
)
from canrig_jax.rig import evaluate_batch, random_sparse_poses

N_PATCHES = 60


@pytest.fixture(scope="module")
def face(ict_face):
    return np.asarray(ict_face.neutral, np.float32), np.asarray(ict_face.faces)


@pytest.fixture(scope="module")
def layout(face):
    return patch_layout(*face, N_PATCHES, rings=2)


@pytest.fixture(scope="module")
def shapes(ict_face):
    """(40, V, 3) real ICT expressions: random sparse poses of the rig."""
    poses = random_sparse_poses(np.random.default_rng(5), 40, ict_face.names)
    return np.asarray(evaluate_batch(ict_face, poses), np.float32)


@pytest.fixture(scope="module")
def basis(face, shapes):
    offsets, _ = pbs_basis(face[0], shapes[:30], 8)
    return offsets


def test_layout_cells_are_connected_and_rows_sum_to_one(face, layout):
    vertices, faces = face
    weights = layout.matrix()
    np.testing.assert_allclose(np.asarray(weights.sum(axis=1)).ravel(), 1.0, atol=1e-5)
    cell = np.asarray(layout.cell)
    seeds = np.asarray(layout.seeds)
    assert np.array_equal(cell[seeds], np.arange(N_PATCHES))  # each seed in its own cell
    adjacency = vertex_adjacency(faces, len(vertices))
    for p in range(N_PATCHES):  # a geodesic Voronoi cell is one connected piece of surface
        members = np.flatnonzero(cell == p)
        n, _ = connected_components(adjacency[members][:, members], directed=False)
        assert n == 1, p
    # each patch covers its cell and at most `rings` rings around it, with weight 1 in the
    # cell before normalisation: a vertex's largest weight is its own cell's
    patches, w = np.asarray(layout.vertex_patches), np.asarray(layout.vertex_weights)
    own = np.take_along_axis(w, np.argmax(patches == cell[:, None], axis=1)[:, None], 1)[:, 0]
    assert np.all(own >= w.max(axis=1) - 1e-6)


def test_covered_by_is_the_union_of_the_selected_patches_vertices(layout):
    selected = np.random.default_rng(0).random(layout.n_patches) < 0.2
    expected = np.zeros(layout.n_vertices, bool)
    patch_vertices = layout.patch_vertices()
    for p in np.flatnonzero(selected):
        expected[patch_vertices[p]] = True
    np.testing.assert_array_equal(layout.covered_by(selected), expected)
    with pytest.raises(ValueError, match="patches"):
        layout.covered_by(selected[:-1])


def test_gather_form_equals_the_sparse_layout_and_zero_is_the_neutral(face, layout, basis):
    neutral = face[0]
    weights = np.random.default_rng(0).normal(size=(N_PATCHES, len(basis))).astype(np.float32)
    ours = np.asarray(pbs_shape(layout, neutral, basis, weights))
    w_layout = layout.matrix()
    per_vertex = w_layout @ weights  # (N, B)
    expected = neutral + np.einsum("nb,bnk->nk", per_vertex, basis)
    np.testing.assert_allclose(ours, expected, atol=1e-4)
    zero = np.asarray(pbs_shape(layout, neutral, basis, np.zeros_like(weights)))
    assert np.array_equal(zero, neutral)


def test_fit_recovers_a_global_combination_and_matches_lstsq(face, layout, basis):
    neutral = face[0]
    x = np.random.default_rng(1).uniform(0, 1, len(basis)).astype(np.float32)
    shape = neutral + np.einsum("b,bnk->nk", x, basis)
    fitted = np.asarray(fit_pbs(layout, neutral, basis, shape, ridge=0.0))
    moved = np.abs(basis).sum(axis=(0, 2)) > 0
    np.testing.assert_allclose(
        np.asarray(pbs_shape(layout, neutral, basis, fitted))[moved], shape[moved], atol=2e-3
    )
    # independent: weighted least squares of one patch with numpy
    w = layout.matrix().tocsc()[:, 7]
    rows, weights = w.indices, w.data
    a = np.transpose(basis[:, rows], (1, 2, 0)).reshape(-1, len(basis))  # (3m, B)
    root = np.repeat(np.sqrt(weights), 3)[:, None]
    target = np.random.default_rng(2).normal(size=shape.shape).astype(np.float32) * 0.1
    solution = np.linalg.lstsq(a * root, (target[rows]).reshape(-1) * root[:, 0], rcond=None)[0]
    ours = np.asarray(fit_pbs(layout, neutral, basis, neutral + target, ridge=0.0))[7]
    np.testing.assert_allclose(ours, solution, rtol=2e-2, atol=2e-2 * np.abs(solution).max())


def test_fit_represents_held_out_shapes(face, layout, basis, shapes):
    """The per-patch fit of held-out shapes is much closer than the best global fit of the
    same basis (patches add locality), and batched equals one at a time."""
    neutral = face[0]
    held_out = shapes[30:]
    fitted = fit_pbs(layout, neutral, basis, held_out)
    patched = np.asarray(pbs_shape(layout, neutral, basis, fitted))
    patch_error = np.linalg.norm(patched - held_out, axis=-1).mean()
    flat = basis.reshape(len(basis), -1).T
    coef = np.linalg.lstsq(flat, (held_out - neutral).reshape(len(held_out), -1).T, rcond=None)[0]
    global_shapes = neutral + (flat @ coef).T.reshape(held_out.shape)
    global_error = np.linalg.norm(global_shapes - held_out, axis=-1).mean()
    assert patch_error < 0.5 * global_error
    one = np.asarray(fit_pbs(layout, neutral, basis, held_out[3]))
    np.testing.assert_allclose(np.asarray(fitted)[3], one, atol=1e-4 * np.abs(one).max())


def test_basis_is_farthest_point_in_shape_space(face, shapes):
    neutral = face[0]
    offsets, index = pbs_basis(neutral, shapes, 5)
    norms = np.linalg.norm((shapes - neutral).reshape(len(shapes), -1), axis=1)
    assert index[0] == np.argmax(norms) and len(set(index.tolist())) == 4
    np.testing.assert_allclose(offsets, shapes[index] - neutral, atol=1e-6)
    check_basis(offsets, len(neutral))  # distinct and non-zero


def test_global_blendshapes_recover_a_basis_combination(face, basis):
    x = np.array([0.3, 0.0, 0.7, 0.1, 0.0, 0.5, 0.2, 0.9], np.float32)[: len(basis)]
    index = np.random.default_rng(3).choice(len(face[0]), 265, replace=False)
    displacements = np.einsum("b,bnk->nk", x, basis)[index]
    ours = np.asarray(global_blendshape_fit(basis, index, displacements, ridge=1e-7))
    np.testing.assert_allclose(ours, x, atol=2e-3)


def test_global_blendshape_dialogue(face, basis, shapes):
    """GBS dialogue replacement on real ICT expressions: the inversion is the ridge fit of
    each frame at every handle (an independent NumPy solve), the edit refits with the moved
    handles at the target, and with no handle moved the edit is the inversion."""
    neutral = face[0]
    index = np.random.default_rng(4).choice(len(neutral), 80, replace=False)
    moved = np.zeros(80, bool)
    moved[:30] = True
    source, target = shapes[30:34], shapes[34:38]
    inverted, edited = global_blendshape_dialogue(basis, neutral, source, target, index, moved)
    a = basis[:, index].reshape(len(basis), -1).astype(np.float64)  # (B, 3H)
    gram = a @ a.T
    matrix = gram + 1e-3 * np.mean(np.diagonal(gram)) * np.eye(len(basis))
    for f in range(4):
        for shape, at in (
            (inverted, source[f][index]),
            (edited, np.where(moved[:, None], target[f][index], source[f][index])),
        ):
            weights = np.linalg.solve(matrix, a @ (at - neutral[index]).ravel())
            expected = neutral + np.einsum("b,bnc->nc", weights, basis)
            np.testing.assert_allclose(np.asarray(shape[f]), expected, atol=2e-4)
    assert np.abs(np.asarray(edited) - np.asarray(inverted)).max() > 1e-2  # the mouth moved
    same, again = global_blendshape_dialogue(
        basis, neutral, source, target, index, np.zeros(80, bool)
    )
    np.testing.assert_allclose(np.asarray(again), np.asarray(same), atol=1e-6)


@pytest.mark.bad_input
def test_global_blendshape_dialogue_names_bad_arguments(face, basis, shapes):
    neutral = face[0]
    index = np.arange(80)
    moved = np.ones(80, bool)
    source, target = shapes[30:34], shapes[34:38]
    with pytest.raises(ValueError, match="moved"):
        global_blendshape_dialogue(basis, neutral, source, target, index, moved[:10])
    with pytest.raises(ValueError, match="target"):
        global_blendshape_dialogue(basis, neutral, source, target[:2], index, moved)


@pytest.mark.slow
def test_local_fit_is_a_masked_ridge_solve_per_patch(face, basis, shapes):
    """local_pbs_fit against an independent NumPy solve per patch on real expressions; a
    patch no mask reaches gets exactly zero weights, zero displacements give exactly zero,
    and with a tiny ridge a basis combination seen by enough handles is recovered."""
    neutral = face[0]
    index = np.random.default_rng(6).choice(len(neutral), 50, replace=False)
    a = basis[:, index].astype(np.float64)  # (B-1, H, 3)
    mask = np.random.default_rng(7).random((5, 50)) * (np.arange(50) < 30)
    mask[2] = 0.0  # a patch no handle reaches
    mask[4, 3:] = 0.0  # one that sees three handles only
    d = (shapes[3] - neutral)[index]
    ours = np.asarray(local_pbs_fit(a.astype(np.float32), d, mask.astype(np.float32), 0.05))
    scale = 0.05 * np.mean(a**2) * 3
    for p in range(5):
        gram = np.einsum("h,bhk,chk->bc", mask[p], a, a) + scale * np.eye(len(a))
        expected = np.linalg.solve(gram, np.einsum("h,bhk,hk->b", mask[p], a, d))
        np.testing.assert_allclose(ours[p], expected, rtol=2e-3, atol=2e-4)
    assert np.all(ours[2] == 0.0)
    zero = local_pbs_fit(a.astype(np.float32), 0 * d, mask.astype(np.float32))
    assert np.all(np.asarray(zero) == 0.0)
    x = np.linspace(0.1, 0.9, len(basis)).astype(np.float32)
    full = np.ones((3, 50), np.float32)
    recovered = local_pbs_fit(a.astype(np.float32), np.einsum("b,bhk->hk", x, a), full, 1e-6)
    np.testing.assert_allclose(np.asarray(recovered), np.tile(x, (3, 1)), atol=5e-3)
    # a normal matrix that is not positive definite (here a negative ridge, the stand-in for
    # rounding) fails its Cholesky: that patch gets zero weights, not NaN; the others solve
    a32, m32 = jnp.asarray(a, jnp.float32), jnp.asarray(mask, jnp.float32)
    factors = local_fit_factor(a32, m32, -1e-3)
    failed = ~np.asarray(factors[1])
    assert failed[2] and not failed.all()  # the unreached patch: gram 0 + negative ridge
    weights = np.asarray(local_fit_solve(factors, a32, m32, jnp.asarray(d)))
    assert np.all(weights[failed] == 0.0) and np.all(np.isfinite(weights))


@pytest.mark.bad_input
@pytest.mark.parametrize(
    ("change", "name"),
    [
        (lambda a, d, m: (a[:, :, :2], d, m), "handle_basis"),
        (lambda a, d, m: (a, d[:10], m), "displacements"),
        (lambda a, d, m: (a, d, m[:, :10]), "mask"),
        (lambda a, d, m: (a, d, -m), "mask"),
        (lambda a, d, m: (a, d * np.nan, m), "displacements"),
    ],
)
def test_bad_input_of_the_local_fit(face, basis, change, name):
    a = basis[:, :20]
    d = np.zeros((20, 3), np.float32)
    m = np.ones((4, 20), np.float32)
    with pytest.raises(ValueError, match=name):
        local_pbs_fit(*change(a, d, m))
    with pytest.raises(ValueError, match="ridge"):
        local_pbs_fit(a, d, m, ridge=0.0)


@pytest.mark.parametrize(
    "case",
    [
        ("n_patches-zero", lambda f, b: patch_layout(*f, 0), "n_patches"),
        ("n_patches-too-many", lambda f, b: patch_layout(*f, len(f[0]) + 1), "n_patches"),
        (
            "basis-zero",
            lambda f, b: check_basis(np.concatenate([b, 0 * b[:1]]), len(f[0])),
            "basis",
        ),
        (
            "basis-repeated",
            lambda f, b: check_basis(np.concatenate([b, 2 * b[:1]]), len(f[0])),
            "basis",
        ),
        ("basis-vertices", lambda f, b: check_basis(b[:, :10], len(f[0])), "basis"),
        ("n_basis-too-many", lambda f, b: pbs_basis(f[0], b[None, 0] + f[0], 3), "n_basis"),
    ],
    ids=lambda c: c[0],
)
def test_bad_input(case, face, basis):
    _, call, name = case
    with pytest.raises(ValueError, match=name):
        call(face, basis)


@pytest.mark.bad_input
def test_bad_input_of_the_fit_and_layout(face, layout, basis):
    neutral = face[0]
    with pytest.raises(ValueError, match="shape"):
        fit_pbs(layout, neutral, basis, neutral[:100])
    bad = neutral.copy()
    bad[5, 0] = np.nan
    with pytest.raises(ValueError, match="shape"):
        fit_pbs(layout, neutral, basis, bad)
    with pytest.raises(ValueError, match="weights"):
        pbs_shape(layout, neutral, basis, np.zeros((N_PATCHES + 1, len(basis))))
    with pytest.raises(ValueError, match="vertex_weights"):
        PatchLayout(
            vertex_patches=layout.vertex_patches,
            vertex_weights=layout.vertex_weights * 1.5,
            seeds=layout.seeds,
            cell=layout.cell,
        )
    with pytest.raises(ValueError, match="handle_index"):
        global_blendshape_fit(basis, np.array([1, 1]), np.zeros((2, 3)))
    assert sp.issparse(layout.matrix())
