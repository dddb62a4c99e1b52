"""``evaluate`` (Racković eq. (5)) against NumPy references, its algebra, gradients and inputs."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrig_jax.rig import BlendshapeRig, Corrective, evaluate, evaluate_batch, load_rig, save_rig
from canrig_jax.rig._blendshape import check_weights

HYPOTHESIS = settings(max_examples=20, deadline=None)


# --- independent references ----------------------------------------------------------------


def numpy_evaluate(rig: BlendshapeRig, weights: np.ndarray) -> np.ndarray:
    """Eq. (5) in float64 NumPy for weights (K,) or (B, K): a plain loop over every stored
    corrective with its dense (V, 3) offsets."""
    weights = np.asarray(weights, np.float64)
    batch = np.atleast_2d(weights)
    mesh = np.repeat(np.asarray(rig.neutral, np.float64)[None], len(batch), axis=0)
    for i in range(rig.n_blendshapes):
        mesh += batch[:, i, None, None] * np.asarray(rig.deltas[i], np.float64)
    for table in rig.correctives:
        dense = table.to_dense(rig.n_vertices)
        for combo, offset in zip(np.asarray(table.indices), dense, strict=True):
            coefficient = np.prod(batch[:, combo], axis=1)
            mesh += coefficient[:, None, None] * offset.astype(np.float64)
    return mesh[0] if weights.ndim == 1 else mesh


def numpy_jacobian(rig: BlendshapeRig, weights: np.ndarray) -> np.ndarray:
    """(V, 3, K) closed-form d f / d w: d_i plus, per corrective containing i, the product
    of the other weights of its combination times its offsets."""
    weights = np.asarray(weights, np.float64)
    jac = np.asarray(rig.deltas, np.float64).copy()  # (K, V, 3)
    for table in rig.correctives:
        dense = table.to_dense(rig.n_vertices)
        for combo, offset in zip(np.asarray(table.indices), dense, strict=True):
            for j, i in enumerate(combo):
                jac[i] += np.prod(np.delete(weights[combo], j)) * offset.astype(np.float64)
    return np.moveaxis(jac, 0, -1)


def _float64_rig(rig: BlendshapeRig) -> BlendshapeRig:
    """The same rig with float64 arrays (call inside ``jax.enable_x64(True)``)."""
    f64 = lambda x: np.asarray(x, np.float64)
    tables = tuple(Corrective(c.indices, c.vertices, f64(c.deltas)) for c in rig.correctives)
    return BlendshapeRig(f64(rig.neutral), f64(rig.deltas), tables, rig.names, rig.faces)


# --- toy rigs for the algebra ----------------------------------------------------------------


@st.composite
def toy_rigs(draw, max_k: int = 5, max_v: int = 4):
    """Small random rigs: K blendshapes, V vertices, a random subset of the combinations of
    every order 2..min(4, K) (index order within a row shuffled), random sorted supports
    (S = V among them, the layout without a scatter)."""
    k = draw(st.integers(2, max_k))
    v = draw(st.integers(1, max_v))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    tables = []
    for order in range(2, min(4, k) + 1):
        combos = list(itertools.combinations(range(k), order))
        chosen = draw(st.lists(st.sampled_from(combos), unique=True, max_size=len(combos)))
        if not chosen:
            continue
        indices = np.array([rng.permutation(c) for c in chosen])
        support = np.sort(rng.choice(v, size=draw(st.integers(1, v)), replace=False))
        deltas = rng.uniform(-1.0, 1.0, (len(chosen), support.size, 3))
        tables.append(Corrective(indices, support, deltas.astype(np.float32)))
    rng.shuffle(tables)  # tables need not be stored by increasing order
    neutral = rng.normal(size=(v, 3)).astype(np.float32)
    deltas = rng.uniform(-1.0, 1.0, (k, v, 3)).astype(np.float32)
    return BlendshapeRig(neutral, deltas, tuple(tables))


def _weights(k: int):
    return st.lists(st.floats(-1.5, 1.5, width=32), min_size=k, max_size=k).map(
        lambda w: np.array(w, np.float32)
    )


@given(data=st.data())
@HYPOTHESIS
def test_toy_rig_matches_numpy_reference(data):
    rig = data.draw(toy_rigs())
    w = data.draw(_weights(rig.n_blendshapes))
    np.testing.assert_allclose(jax.jit(evaluate)(rig, w), numpy_evaluate(rig, w), rtol=0, atol=1e-4)


@pytest.mark.slow
@given(data=st.data())
@HYPOTHESIS
def test_rig_is_affine_in_each_weight(data):
    """Multilinearity: with the other weights fixed, f(a) - 2 f((a+b)/2) + f(b) = 0."""
    rig = data.draw(toy_rigs())
    k = rig.n_blendshapes
    w = data.draw(_weights(k))
    i = data.draw(st.integers(0, k - 1))
    a, b = data.draw(st.tuples(st.floats(-2, 2, width=32), st.floats(-2, 2, width=32)))
    at = lambda t: np.asarray(evaluate(rig, _set(w, i, t)), np.float64)
    second_difference = at(a) - 2 * at(0.5 * (a + b)) + at(b)
    np.testing.assert_allclose(second_difference, 0.0, atol=2e-4)


def _set(w: np.ndarray, i: int, t: float) -> np.ndarray:
    w = w.copy()
    w[i] = t
    return w


@given(data=st.data())
@HYPOTHESIS
def test_exact_at_hypercube_corners(data):
    """At 1_S the rig is the neutral + deltas of S + every corrective whose set lies in S."""
    rig = data.draw(toy_rigs())
    k = rig.n_blendshapes
    subset = data.draw(st.sets(st.integers(0, k - 1)))
    corner = np.zeros(k, np.float32)
    corner[list(subset)] = 1.0
    expected = np.asarray(rig.neutral, np.float64) + sum(
        (np.asarray(rig.deltas[i], np.float64) for i in subset), np.zeros((rig.n_vertices, 3))
    )
    for table in rig.correctives:
        dense = table.to_dense(rig.n_vertices)
        for combo, offset in zip(np.asarray(table.indices).tolist(), dense, strict=True):
            if set(combo) <= subset:
                expected = expected + offset
    np.testing.assert_allclose(evaluate(rig, corner), expected, rtol=0, atol=1e-4)


@given(rig=toy_rigs())
@HYPOTHESIS
def test_zero_weights_give_the_neutral_exactly(rig):
    np.testing.assert_array_equal(evaluate(rig, np.zeros(rig.n_blendshapes)), rig.neutral)


# --- the real ict-quartic rig ----------------------------------------------------------------


def test_ict_quartic_matches_numpy_at_live_link_frames(ict_quartic, livelink_weights):
    frames = livelink_weights[::12]  # 15 of the 180 frames
    batch = evaluate_batch(ict_quartic, frames)
    np.testing.assert_allclose(batch, numpy_evaluate(ict_quartic, frames), rtol=0, atol=1e-5)


def test_ict_quartic_matches_numpy_at_sparse_poses(ict_quartic, sparse_poses):
    expected = numpy_evaluate(ict_quartic, sparse_poses)
    run = jax.jit(evaluate)  # one program for the 16 poses (op by op: test_jit_vmap_equals_...)
    for w, mesh in zip(sparse_poses, expected, strict=True):
        np.testing.assert_allclose(run(ict_quartic, w), mesh, rtol=0, atol=1e-5)


def test_correctives_matter_on_the_real_rig(ict_quartic):
    """At the jawOpen + mouthClose corner the quartic rig departs from the linear one by its
    pair corrective (> 5 mm), and by exactly that corrective."""
    corner = np.zeros(ict_quartic.n_blendshapes, np.float32)
    i, j = ict_quartic.index(["jawOpen", "mouthClose"])
    corner[[i, j]] = 1.0
    diff = np.asarray(evaluate(ict_quartic, corner) - evaluate(ict_quartic.linear(), corner))
    assert np.linalg.norm(diff, axis=1).max() > 0.5
    pairs = ict_quartic.corrective(2)
    row = [r for r, c in enumerate(np.asarray(pairs.indices).tolist()) if sorted(c) == [i, j]]
    assert len(row) == 1
    np.testing.assert_allclose(diff, pairs.to_dense(ict_quartic.n_vertices)[row[0]], atol=1e-5)


def test_linear_rig_is_neutral_plus_weighted_deltas(ict_quartic, livelink_weights, sparse_poses):
    linear = ict_quartic.linear()
    assert linear.correctives == () and linear.names == ict_quartic.names
    np.testing.assert_array_equal(linear.faces, ict_quartic.faces)
    neutral = np.asarray(ict_quartic.neutral, np.float64)
    deltas = np.asarray(ict_quartic.deltas, np.float64)
    for w in [*livelink_weights[::45], *sparse_poses[:4]]:
        expected = neutral + np.tensordot(w.astype(np.float64), deltas, axes=1)
        np.testing.assert_allclose(evaluate(linear, w), expected, rtol=0, atol=1e-5)


def test_jit_vmap_equals_a_loop_of_evaluate(ict_quartic, livelink_weights, sparse_poses):
    poses = np.concatenate([livelink_weights[::30], sparse_poses[:6]])
    batch = evaluate_batch(ict_quartic, poses)
    loop = np.stack([np.asarray(evaluate(ict_quartic, w)) for w in poses])
    assert batch.shape == (len(poses), ict_quartic.n_vertices, 3)
    np.testing.assert_allclose(batch, loop, rtol=0, atol=1e-5)


# --- gradients ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ict_quartic_f64(ict_quartic):
    """The ict-quartic rig in float64; use it inside ``jax.enable_x64(True)`` only."""
    with jax.enable_x64(True):
        return _float64_rig(ict_quartic)


def test_jacobian_matches_closed_form_on_ict_quartic(ict_quartic, ict_quartic_f64, sparse_poses):
    """jax.jacfwd of evaluate (float64) against the closed-form derivative of eq. (5)."""
    w = sparse_poses[3].astype(np.float64)
    w[ict_quartic.index(["jawOpen", "mouthClose", "mouthSmile_L"])] = [0.7, 0.4, 0.6]
    with jax.enable_x64(True):
        jacobian = jax.jit(jax.jacfwd(evaluate, argnums=1))
        jac = np.asarray(jacobian(ict_quartic_f64, jnp.asarray(w)))
    assert jac.dtype == np.float64
    np.testing.assert_allclose(jac, numpy_jacobian(ict_quartic, w), rtol=0, atol=1e-9)


def test_gradient_matches_central_differences_on_ict_quartic(
    ict_quartic, ict_quartic_f64, sparse_poses
):
    """jax.grad of a scalar loss of evaluate against central finite differences (float64),
    along coordinate axes (active and inactive channels) and random directions."""
    rng = np.random.default_rng(0)
    w = sparse_poses[5].astype(np.float64)
    active = ict_quartic.index(["jawOpen", "mouthClose", "mouthFunnel"])
    w[active] = [0.5, 0.3, 0.8]
    eye = np.eye(w.size)
    directions = np.concatenate(
        [eye[active], eye[np.flatnonzero(w == 0)[:4]], rng.normal(size=(3, w.size))]
    )
    with jax.enable_x64(True):
        target = jnp.asarray(numpy_evaluate(ict_quartic, rng.uniform(0, 0.5, w.size)))
        # rig and target are arguments, not closed-over constants (slow to compile)
        loss = lambda rig, x, y: jnp.sum((evaluate(rig, x) - y) ** 2)
        grad = np.asarray(jax.jit(jax.grad(loss, 1))(ict_quartic_f64, jnp.asarray(w), target))
        step = 1e-6
        probes = jnp.asarray(np.concatenate([w + step * directions, w - step * directions]))
        losses = jax.jit(jax.vmap(loss, (None, 0, None)))(ict_quartic_f64, probes, target)
        plus, minus = np.split(np.asarray(losses), 2)
    central = (plus - minus) / (2 * step)
    assert np.abs(grad).max() > 1.0  # not trivially zero
    np.testing.assert_allclose(directions @ grad, central, rtol=1e-6, atol=1e-5)


@given(data=st.data())
@settings(max_examples=10, deadline=None)
def test_toy_jacobian_matches_closed_form(data):
    rig = data.draw(toy_rigs())
    w = data.draw(_weights(rig.n_blendshapes))
    jac = jax.jit(jax.jacrev(evaluate, argnums=1))(rig, jnp.asarray(w))
    np.testing.assert_allclose(jac, numpy_jacobian(rig, w), rtol=0, atol=1e-4)


# --- bad input: ValueError naming the argument, before any tracing ------------------------------


@pytest.fixture(scope="module")
def small_rig():
    rng = np.random.default_rng(1)
    neutral = rng.normal(size=(6, 3)).astype(np.float32)
    deltas = rng.normal(size=(4, 6, 3)).astype(np.float32)
    pairs = Corrective([[0, 1], [2, 3]], [1, 4], rng.normal(size=(2, 2, 3)))
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    return BlendshapeRig(neutral, deltas, (pairs,), ("a", "b", "c", "d"), faces)


@pytest.mark.bad_input
@pytest.mark.parametrize("shape", [(5,), (3,), (2, 4), (), (4, 1)])
def test_weights_of_wrong_shape_raise(small_rig, shape):
    with pytest.raises(ValueError, match="weights"):
        evaluate(small_rig, np.zeros(shape, np.float32))
    with pytest.raises(ValueError, match="weights"):
        check_weights(small_rig, np.zeros(shape, np.float32))


def test_wrong_shape_raises_value_error_under_jit_too(small_rig):
    """The shape check is plain Python, so it fires while tracing, not as a JAX error."""
    with pytest.raises(ValueError, match="weights"):
        jax.jit(evaluate)(small_rig, jnp.zeros(5))
    with pytest.raises(ValueError, match="weights"):
        jax.vmap(evaluate, (None, 0))(small_rig, jnp.zeros((2, 3)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_weights_raise(small_rig, bad):
    w = np.array([0.1, bad, 0.2, 0.3], np.float32)
    with pytest.raises(ValueError, match="weights"):
        evaluate(small_rig, w)
    with pytest.raises(ValueError, match="weights"):
        evaluate(small_rig, jnp.asarray(w))


@pytest.mark.parametrize("bad_index", [4, 7, -1])
def test_corrective_index_out_of_range_raises(small_rig, bad_index):
    table = Corrective([[0, 1], [2, bad_index]], [1, 4], np.zeros((2, 2, 3)))
    with pytest.raises(ValueError, match="correctives"):
        BlendshapeRig(small_rig.neutral, small_rig.deltas, (table,))


@pytest.mark.parametrize("row", [[1, 1], [2, 0, 2], [3, 1, 0, 3]])
def test_repeated_index_within_a_combination_raises(row):
    with pytest.raises(ValueError, match="indices"):
        Corrective([row], [0], np.zeros((1, 1, 3)))


@pytest.mark.parametrize("vertices", [[3, 1], [1, 1], [0, 2, 2]])
def test_unsorted_or_repeated_support_vertices_raise(vertices):
    with pytest.raises(ValueError, match="vertices"):
        Corrective([[0, 1]], vertices, np.zeros((1, len(vertices), 3)))


def test_corrective_support_out_of_range_raises(small_rig):
    table = Corrective([[0, 1]], [2, 6], np.zeros((1, 2, 3)))
    with pytest.raises(ValueError, match="correctives"):
        BlendshapeRig(small_rig.neutral, small_rig.deltas, (table,))


@pytest.mark.parametrize("faces", [[[0, 1, 6]], [[0, -1, 2]], [[0, 1]]])
def test_bad_faces_raise(small_rig, faces):
    with pytest.raises(ValueError, match="faces"):
        BlendshapeRig(small_rig.neutral, small_rig.deltas, faces=np.array(faces))


@pytest.mark.parametrize("shape", [(4, 5, 3), (4, 6, 2), (6, 3)])
def test_deltas_shape_mismatch_with_neutral_raises(small_rig, shape):
    with pytest.raises(ValueError, match="deltas"):
        BlendshapeRig(small_rig.neutral, np.zeros(shape, np.float32))


def test_corrective_deltas_shape_mismatch_raises():
    with pytest.raises(ValueError, match="deltas"):
        Corrective([[0, 1], [1, 2]], [0, 1, 2], np.zeros((2, 2, 3)))


@pytest.mark.parametrize("names", [("a", "b", "c"), tuple("abcde"), ("a", "a", "b", "c")])
def test_names_count_mismatch_or_duplicates_raise(small_rig, names):
    with pytest.raises(ValueError, match="names"):
        BlendshapeRig(small_rig.neutral, small_rig.deltas, names=names)


def test_non_finite_rig_arrays_raise(small_rig):
    neutral = np.asarray(small_rig.neutral).copy()
    neutral[2, 1] = np.nan
    with pytest.raises(ValueError, match="neutral"):
        BlendshapeRig(neutral, small_rig.deltas)
    with pytest.raises(ValueError, match="deltas"):
        Corrective([[0, 1]], [0], np.full((1, 1, 3), np.inf))


def test_two_tables_of_one_order_raise(small_rig):
    table = Corrective([[0, 1]], [0], np.zeros((1, 1, 3)))
    with pytest.raises(ValueError, match="correctives"):
        BlendshapeRig(small_rig.neutral, small_rig.deltas, (table, table))


# --- storage ----------------------------------------------------------------------------------


def test_from_dense_keeps_exactly_the_support(small_rig):
    rng = np.random.default_rng(3)
    dense = np.zeros((2, 6, 3), np.float32)
    dense[0, 1] = [0.3, 0.0, 0.0]
    dense[1, 4] = rng.normal(size=3)
    dense[1, 5] = [1e-6, 0.0, 0.0]  # below the tolerance: dropped
    table = Corrective.from_dense([[0, 1], [2, 3]], dense, support_tol=1e-5)
    assert np.asarray(table.vertices).tolist() == [1, 4]
    expected = dense.copy()
    expected[1, 5] = 0.0
    np.testing.assert_array_equal(table.to_dense(6), expected)


def _assert_rigs_identical(a: BlendshapeRig, b: BlendshapeRig):
    assert a.names == b.names
    for x, y in [(a.neutral, b.neutral), (a.deltas, b.deltas), (a.faces, b.faces)]:
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(x, y)
    assert [c.order for c in a.correctives] == [c.order for c in b.correctives]
    for c, d in zip(a.correctives, b.correctives, strict=True):
        for x, y in [(c.indices, d.indices), (c.vertices, d.vertices), (c.deltas, d.deltas)]:
            assert np.asarray(x).dtype == np.asarray(y).dtype
            np.testing.assert_array_equal(x, y)


def test_save_load_round_trip_is_exact(ict_quartic, tmp_path, sparse_poses):
    path = save_rig(tmp_path / "rig.npz", ict_quartic)
    loaded = load_rig(path)
    _assert_rigs_identical(ict_quartic, loaded)
    np.testing.assert_array_equal(
        evaluate(loaded, sparse_poses[0]), evaluate(ict_quartic, sparse_poses[0])
    )
    assert [p.name for p in tmp_path.iterdir()] == ["rig.npz"]  # no temporary left behind


def test_save_load_round_trip_without_faces_or_names(small_rig, tmp_path):
    bare = BlendshapeRig(small_rig.neutral, small_rig.deltas, small_rig.correctives)
    loaded = load_rig(save_rig(tmp_path / "bare.npz", bare))
    assert loaded.faces is None and loaded.names == ()
    _assert_rigs_identical(bare, BlendshapeRig(loaded.neutral, loaded.deltas, loaded.correctives))


def test_evaluate_batch_compiles_once_per_shape(ict_quartic, livelink_weights):
    """Chunks of one size share one compilation whatever the number of poses, and a batch
    equals evaluate pose by pose."""
    compiled = []

    def listener(event, duration, fun_name="", **kwargs):
        if event == "/jax/core/compile/backend_compile_duration" and "evaluate_many" in fun_name:
            compiled.append(fun_name)

    jax.monitoring.register_event_duration_secs_listener(listener)
    frames = livelink_weights[:23]
    outs = [np.asarray(evaluate_batch(ict_quartic, frames[:n], chunk=8)) for n in (9, 17, 23)]
    assert len(compiled) <= 1  # one (8, K) program for all three batch sizes (0 if cached)
    again = len(compiled)
    evaluate_batch(ict_quartic, frames[:12], chunk=8)
    assert len(compiled) == again
    single = np.stack([np.asarray(evaluate(ict_quartic, w)) for w in frames])
    np.testing.assert_allclose(outs[-1], single, atol=1e-5)
    np.testing.assert_array_equal(outs[0], outs[-1][:9])
