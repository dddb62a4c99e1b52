"""DiffusionNet in equinox: diffusion against SciPy, discretisation agnosticism, rotation
invariance, batching by padding, gradients, bad input."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from canrig_jax.autorig import DiffusionNet, heat_kernel_signature, hks_times
from canrig_jax.autorig._diffusion import LearnedDiffusion, implicit_diffusion, spectral_diffusion
from canrig_jax.autorig._features import mass_weighted_mean
from canrig_jax.data import FACE, load_ict, load_mediapipe_face
from canrig_jax.mesh import MeshOperators, decimate, flip_quad_split, pad_vertices, stack_operators
from canrig_jax.mesh._operators import mesh_geometry

METHODS = ("spectral", "implicit")


@pytest.fixture(scope="module")
def mediapipe_geometry(data_dir):
    """MediaPipe canonical face (468 vertices) with the full eigenbasis."""
    face = load_mediapipe_face(data_dir)
    return mesh_geometry(face.neutral, face.faces, k=468, cache=False)


@pytest.fixture(scope="module")
def ict_face(data_dir):
    return load_ict(data_dir, parts=FACE)


def _smooth_field(vertices):
    """Two smooth functions of position (cm), as (V, 2)."""
    x, y, z = vertices[:, 0], vertices[:, 1], vertices[:, 2]
    return np.stack([np.sin(x / 2.0) + 0.3 * z, np.cos(y / 3.0) * (1 + 0.1 * x)], axis=1)


# -- diffusion against independent computations -----------------------------------------------


def test_spectral_diffusion_with_the_full_basis_equals_expm(mediapipe_geometry):
    g = mediapipe_geometry
    u = _smooth_field(g.vertices)
    times = np.array([0.3, 4.0])
    ops = MeshOperators.from_geometry(g)
    out = np.asarray(spectral_diffusion(jnp.asarray(u, jnp.float32), jnp.asarray(times), ops))
    operator = -(sp.diags(1.0 / g.mass) @ g.laplacian)
    expected = np.stack(
        [spla.expm_multiply(t * operator, u[:, c]) for c, t in enumerate(times)], axis=1
    )
    assert np.abs(out - expected).max() < 1e-4 * np.abs(expected).max()


@pytest.mark.slow  # 12-21 s; the default run stays under 10 min on 2 cores
def test_implicit_diffusion_equals_a_sparse_solve(mediapipe_geometry):
    g = mediapipe_geometry
    u = _smooth_field(g.vertices)
    times = np.array([0.3, 4.0])
    ops = MeshOperators.from_geometry(g)
    out = np.asarray(implicit_diffusion(jnp.asarray(u, jnp.float32), jnp.asarray(times), ops))
    mass = sp.diags(g.mass)
    expected = np.stack(
        [
            spla.spsolve((mass + t * g.laplacian).tocsc(), g.mass * u[:, c])
            for c, t in enumerate(times)
        ],
        axis=1,
    )
    assert np.abs(out - expected).max() < 1e-4 * np.abs(expected).max()


@pytest.mark.parametrize("method", METHODS)
def test_gradient_with_respect_to_diffusion_times_matches_finite_differences(
    mediapipe_geometry, method
):
    ops = MeshOperators.from_geometry(mediapipe_geometry)
    u = jnp.asarray(_smooth_field(mediapipe_geometry.vertices), jnp.float32)
    weights = jnp.asarray(np.random.default_rng(0).standard_normal(u.shape), jnp.float32)
    layer = LearnedDiffusion(2, method, init_time=1.0)

    @jax.jit
    def loss(times):
        return jnp.sum(weights * eqx.tree_at(lambda m: m.times, layer, times)(u, ops))

    times = jnp.array([0.7, 2.5])
    grad = np.asarray(jax.grad(loss)(times))
    step = 1e-2
    finite = [
        (loss(times.at[c].add(step)) - loss(times.at[c].add(-step))) / (2 * step) for c in range(2)
    ]
    np.testing.assert_allclose(grad, np.asarray(finite), rtol=2e-2, atol=1e-3)


@pytest.mark.parametrize("method", [pytest.param("spectral", marks=pytest.mark.slow), "implicit"])
def test_diffusion_agrees_across_triangulations_of_the_ict_face(ict_face, tmp_path, method):
    """Discretisation agnosticism: the same smooth field diffused for t = 1 cm^2 on ICT's
    quad split and on the other diagonal, and on a 3,000-vertex decimation, compared at
    corresponding points (identity / surface map). Tolerance: 3 % (max) and 0.3 % (mean)
    of the field's range (measured: see experiments/results/mesh_foundations)."""
    k = 128 if method == "spectral" else 0
    original = mesh_geometry(ict_face.neutral, ict_face.faces, k=k, cache=tmp_path)
    flipped = flip_quad_split(ict_face.neutral, ict_face.faces)
    coarse = decimate(ict_face.neutral, ict_face.faces, 3000)

    def diffuse(vertices, faces):
        geometry = mesh_geometry(vertices, faces, k=k, cache=tmp_path)
        layer = LearnedDiffusion(2, method, init_time=1.0)
        u = jnp.asarray(_smooth_field(geometry.vertices), jnp.float32)
        return np.asarray(layer(u, MeshOperators.from_geometry(geometry)))

    reference = diffuse(original.vertices, original.faces)
    scale = np.ptp(reference, axis=0)
    for remeshed in (flipped, coarse):
        other = diffuse(remeshed.vertices, remeshed.faces)
        difference = np.abs(other - remeshed.map.carry(reference)) / scale
        assert difference.max() < 0.03, (remeshed.method, difference.max())
        assert difference.mean() < 0.003, (remeshed.method, difference.mean())


# -- the network ------------------------------------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
def test_outputs_are_invariant_to_a_rigid_rotation(data_dir, method):
    face = load_mediapipe_face(data_dir)
    rotation = np.linalg.qr(np.random.default_rng(3).standard_normal((3, 3)))[0]
    rotation *= np.sign(np.linalg.det(rotation))
    moved = face.neutral.astype(np.float64) @ rotation.T + np.array([1.0, -2.0, 0.5])
    model = eqx.filter_jit(
        DiffusionNet(16, 5, 32, 2, method=method, init_time=0.5, key=jax.random.key(0))
    )
    outputs = []
    for vertices in (face.neutral, moved):
        geometry = mesh_geometry(vertices, face.faces, k=468, cache=False)
        ops = MeshOperators.from_geometry(geometry)
        features = heat_kernel_signature(ops, jnp.asarray(hks_times(geometry.eigenvalues, 16)))
        outputs.append(np.asarray(model(features, ops)))
    scale = np.abs(outputs[0]).max()
    assert np.abs(outputs[0] - outputs[1]).max() < 1e-3 * scale


@pytest.mark.slow  # 12-21 s; the default run stays under 10 min on 2 cores
def test_batching_by_padding_equals_one_mesh_at_a_time(data_dir, ict_face):
    mediapipe = load_mediapipe_face(data_dir)
    coarse = decimate(ict_face.neutral, ict_face.faces, 700)
    meshes = [(mediapipe.neutral, mediapipe.faces), (coarse.vertices, coarse.faces)]
    geometries = [mesh_geometry(v, f, k=48, cache=False) for v, f in meshes]
    operators = [MeshOperators.from_geometry(g) for g in geometries]
    features = [jnp.asarray(g.vertices, jnp.float32) for g in geometries]
    stacked = stack_operators(operators)
    batch = pad_vertices(features)
    cases = (
        ("implicit", "vertices", lambda g: g.n_vertices),
        ("spectral", "faces", lambda g: len(g.faces)),
    )
    for method, outputs, size in cases:
        model = DiffusionNet(
            3, 4, 8, 1, method=method, outputs=outputs, init_time=0.3, key=jax.random.key(1)
        )
        together = np.asarray(eqx.filter_jit(eqx.filter_vmap(model))(batch, stacked))
        for i, (g, ops, x) in enumerate(zip(geometries, operators, features, strict=True)):
            alone = np.asarray(eqx.filter_jit(model)(x, ops))
            n = size(g)
            np.testing.assert_allclose(together[i, :n], alone, rtol=1e-4, atol=1e-4)
            assert np.all(together[i, n:] == 0)  # padding stays zero
    # global pooling ignores the padding
    pooled = jax.vmap(mass_weighted_mean)(batch, stacked)
    for i, (ops, x) in enumerate(zip(operators, features, strict=True)):
        np.testing.assert_allclose(pooled[i], mass_weighted_mean(x, ops), rtol=1e-5)


def test_mass_weighted_mean_is_the_area_average(mediapipe_geometry):
    ops = MeshOperators.from_geometry(mediapipe_geometry)
    values = jnp.asarray(_smooth_field(mediapipe_geometry.vertices), jnp.float32)
    expected = mediapipe_geometry.mass @ np.asarray(values) / mediapipe_geometry.mass.sum()
    np.testing.assert_allclose(np.asarray(mass_weighted_mean(values, ops)), expected, rtol=1e-5)


def test_face_outputs_are_the_mean_of_the_corners(mediapipe_geometry):
    ops = MeshOperators.from_geometry(mediapipe_geometry)
    x = jnp.asarray(mediapipe_geometry.vertices, jnp.float32)
    key = jax.random.key(4)
    at_vertices = eqx.filter_jit(DiffusionNet(3, 2, 8, 1, key=key))(x, ops)
    at_faces = eqx.filter_jit(DiffusionNet(3, 2, 8, 1, outputs="faces", key=key))(x, ops)
    np.testing.assert_allclose(
        np.asarray(at_faces), np.asarray(at_vertices)[mediapipe_geometry.faces].mean(1), rtol=1e-5
    )


@pytest.mark.parametrize("method", [pytest.param("spectral", marks=pytest.mark.slow), "implicit"])
def test_jit_and_grad_give_finite_gradients_for_every_parameter(mediapipe_geometry, method):
    ops = MeshOperators.from_geometry(mediapipe_geometry)
    x = jnp.asarray(mediapipe_geometry.vertices, jnp.float32)
    model = DiffusionNet(3, 3, 8, 1, method=method, init_time=0.5, key=jax.random.key(5))

    @eqx.filter_jit
    @eqx.filter_grad
    def grad(m):
        return jnp.mean((m(x, ops) - x) ** 2)

    grads = grad(model)
    leaves = jax.tree.leaves(eqx.filter(grads, eqx.is_inexact_array))
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)
    for block in grads.blocks:
        assert float(jnp.abs(block.diffusion.times).sum()) > 0


def test_isolated_vertices_stay_at_zero(mediapipe_geometry):
    g = mediapipe_geometry
    vertices = np.concatenate([g.vertices, g.vertices[:1] + 50.0])
    geometry = mesh_geometry(vertices, g.faces, k=64, cache=False)
    ops = MeshOperators.from_geometry(geometry)
    x = jnp.ones((len(vertices), 2))
    for method in METHODS:
        out = np.asarray(eqx.filter_jit(LearnedDiffusion(2, method, init_time=1.0))(x, ops))
        assert np.all(np.isfinite(out)) and np.all(out[-1] == 0)
    model = DiffusionNet(2, 2, 8, 1, method="implicit", init_time=1.0, key=jax.random.key(6))
    out = np.asarray(eqx.filter_jit(model)(x, ops))
    assert np.all(np.isfinite(out)) and np.all(out[-1] == 0)


def test_bad_input_raises_naming_the_argument(mediapipe_geometry):
    ops = MeshOperators.from_geometry(mediapipe_geometry)
    model = DiffusionNet(3, 2, 8, 1, key=jax.random.key(7))
    with pytest.raises(ValueError, match="^features:"):
        model(jnp.zeros((10, 3)), ops)
    with pytest.raises(ValueError, match="^features:"):
        model(jnp.zeros((ops.n_vertices, 4)), ops)
    with pytest.raises(ValueError, match="^features:"):
        model(jnp.full((ops.n_vertices, 3), jnp.nan), ops)
    with pytest.raises(ValueError, match="^method:"):
        DiffusionNet(3, 2, method="explicit", key=jax.random.key(0))
    with pytest.raises(ValueError, match="^outputs:"):
        DiffusionNet(3, 2, outputs="edges", key=jax.random.key(0))
    with pytest.raises(ValueError, match="^width:"):
        DiffusionNet(3, 2, width=0, key=jax.random.key(0))
