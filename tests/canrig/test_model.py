"""CANRig and the shape-preserving variant: the two exact properties, cached queries,
run-time radius/falloff/beta without recompiling, bad input."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.canrig import CLAMP, CANRig, NeuralRig, ShapePreservingCANRig, influence_mask
from canrig_jax.canrig._rig import deform

VARIANTS = [
    (CANRig, {}),
    (ShapePreservingCANRig, {}),
    # the options of the standard configuration: positional encoding, query modulation
    (CANRig, {"fourier": 6, "query_modulation": True}),
    (
        ShapePreservingCANRig,
        {"fourier": 6, "query_modulation": True, "linear_skip": True, "value_position": True},
    ),
]


def _variant_id(variant):
    cls, kwargs = variant
    return cls.__name__ + "".join(f"-{k}" for k in kwargs)


@pytest.fixture(scope="module")
def face(ict_face):
    return np.asarray(ict_face.neutral, np.float32), np.asarray(ict_face.faces)


@pytest.fixture(scope="module", params=VARIANTS, ids=_variant_id)
def neural_rig(request, face):
    cls, kwargs = request.param
    model = cls(face[0], key=jax.random.PRNGKey(3), **kwargs)
    return NeuralRig(model, *face)


@pytest.fixture(scope="module")
def placed(neural_rig):
    index = np.random.default_rng(0).choice(neural_rig.n_vertices, 60, replace=False)
    return neural_rig.handles(index)


@pytest.fixture(scope="module")
def other_shape(ict_face, sparse_poses):
    """A real ICT expression as the base shape (evaluated once for the module)."""
    from canrig_jax.rig import evaluate

    return np.asarray(evaluate(ict_face, sparse_poses[0]))


def test_zero_displacements_give_the_base_shape_exactly(neural_rig, placed, other_shape):
    zeros = np.zeros((placed.n_handles, 3), np.float32)
    for base in (None, other_shape):
        expected = neural_rig.canonical if base is None else base
        for radius in (0.5, 2.0, 8.0):
            out = neural_rig(placed, zeros, radius, 3.0, base=base)
            assert np.array_equal(np.asarray(out), np.asarray(expected))


def test_vertices_outside_every_clamped_mask_do_not_move(neural_rig, placed, other_shape):
    rng = np.random.default_rng(1)
    displacements = rng.normal(0, 0.5, (placed.n_handles, 3)).astype(np.float32)
    base = other_shape
    out = np.asarray(neural_rig(placed, displacements, 1.0, 3.0, base=base, beta=0.5))
    mask = np.asarray(influence_mask(placed.distance, np.ones(60), np.full(60, 3.0), CLAMP))
    outside = mask.max(axis=1) == 0.0
    assert 1000 < outside.sum() < len(base)
    assert np.array_equal(out[outside], base[outside])
    assert np.abs(out[~outside] - base[~outside]).max() > 1e-4  # and the region does move


def test_cached_queries_equal_uncached(neural_rig):
    uncached = neural_rig.model.encode_queries(neural_rig.canonical)
    np.testing.assert_allclose(np.asarray(neural_rig.queries), np.asarray(uncached), atol=1e-6)


def test_radius_falloff_beta_change_without_recompiling(neural_rig, placed):
    displacements = np.full((placed.n_handles, 3), 0.1, np.float32)
    before = deform._cached._cache_size() if hasattr(deform, "_cached") else None
    outs = [
        neural_rig(placed, displacements, r, f, beta=b, dense=True)
        for r, f, b in ((1.0, 2.0, 0.0), (3.0, 5.0, 1.0), (2.0, 3.0, -1.0))
    ]
    if before is not None:
        assert deform._cached._cache_size() - before <= 1
    assert not np.allclose(outs[0], outs[1])


@pytest.mark.slow
def test_positional_encoding_and_query_modulation(face):
    """fourier = L gives 3 + 6L query/key inputs (sin, cos of pi 2^k x); the query modulation
    makes the output depend on the vertex's query, and the model stays zero-preserving."""
    plain = ShapePreservingCANRig(face[0], key=jax.random.PRNGKey(0))
    model = ShapePreservingCANRig(
        face[0], fourier=4, query_modulation=True, key=jax.random.PRNGKey(0)
    )
    points = jnp.asarray(face[0][:7])
    encoded = model.encode_position(points)
    assert encoded.shape == (7, 3 + 6 * 4)
    x = model.normalise(points)
    np.testing.assert_allclose(encoded[:, :3], x, atol=1e-6)
    np.testing.assert_allclose(encoded[:, 3 + 3], jnp.sin(8 * jnp.pi * x[:, 0]), atol=1e-5)
    assert plain.encode_position(points).shape == (7, 3)
    queries = model.encode_queries(points)
    d = jnp.ones((2, 3)) * 0.1
    mask = jnp.full((7, 2), 0.5)
    out = model(queries, points, points[:2], points[:2], d, mask, 0.0)
    without = eqx.tree_at(lambda m: m.query_modulation, model, None)
    other = without(queries, points, points[:2], points[:2], d, mask, 0.0)
    assert not np.allclose(np.asarray(out), np.asarray(other))
    zero = model(queries, points, points[:2], points[:2], 0 * d, mask, 0.0)
    assert np.array_equal(np.asarray(zero), np.asarray(points))


def test_handles_positions_come_from_canonical_and_base(face):
    """Moving the base shape changes the SP output only through the base inputs."""
    model = ShapePreservingCANRig(face[0], key=jax.random.PRNGKey(0))
    canonical = jnp.asarray(face[0][:200])
    queries = eqx.filter_jit(type(model).encode_queries)(model, canonical)
    d = jnp.ones((5, 3)) * 0.1
    mask = jnp.full((200, 5), 0.5)
    call = eqx.filter_jit(lambda m, *args: m(*args))
    a = call(model, queries, canonical, canonical[:5], canonical[:5], d, mask, 0.0)
    b = call(model, queries, canonical + 1.0, canonical[:5], canonical[:5] + 1.0, d, mask, 0.0)
    assert not np.allclose(np.asarray(a), np.asarray(b) - 1.0)  # modulated by the base


def _bad_calls(rig, handles):
    h = handles.n_handles
    ok = np.zeros((h, 3), np.float32)
    nan = ok.copy()
    nan[0, 0] = np.nan
    return [
        ("index", lambda: rig.handles(np.array([], np.int64))),
        ("index", lambda: rig.handles(np.array([0, rig.n_vertices]))),
        ("index", lambda: rig.handles(np.array([-1]))),
        ("radius", lambda: rig(handles, ok, 0.0, 3.0)),
        ("radius", lambda: rig(handles, ok, np.full(h, -1.0), 3.0)),
        ("falloff", lambda: rig(handles, ok, 1.0, 0.0)),
        ("falloff", lambda: rig(handles, ok, 1.0, np.ones(h + 1))),
        ("displacements", lambda: rig(handles, nan, 1.0, 3.0)),
        ("displacements", lambda: rig(handles, ok[:-1], 1.0, 3.0)),
        ("base", lambda: rig(handles, ok, 1.0, 3.0, base=np.zeros((10, 3)))),
        ("base", lambda: rig(handles, ok, 1.0, 3.0, base=np.full((rig.n_vertices, 3), np.inf))),
        ("handles", lambda: rig(None, ok, 1.0, 3.0)),
        ("handles", lambda: rig(dataclasses.replace(handles, block_distance=ok), ok, 1.0, 3.0)),
    ]


@pytest.mark.bad_input
def test_bad_input_raises_before_jit(neural_rig, placed):
    for name, call in _bad_calls(neural_rig, placed):
        with pytest.raises(ValueError, match=name):
            call()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"latent": 30}, "latent"),
        ({"n_layers": 0}, "n_layers"),
        ({"clamp": 0.7}, "clamp"),
        ({"fourier": -1}, "fourier"),
    ],
)
def test_bad_hyper_parameters(face, kwargs, match):
    with pytest.raises(ValueError, match=match):
        CANRig(face[0], key=jax.random.PRNGKey(0), **kwargs)


def test_block_sparse_forward_equals_dense(neural_rig, placed, other_shape):
    rng = np.random.default_rng(5)
    displacements = rng.normal(0, 0.5, (placed.n_handles, 3)).astype(np.float32)
    base = other_shape
    for radius in (0.7, 3.0):
        blocked = neural_rig(placed, displacements, radius, 3.0, base=base, beta=0.3)
        dense = neural_rig(placed, displacements, radius, 3.0, base=base, beta=0.3, dense=True)
        np.testing.assert_allclose(np.asarray(blocked), np.asarray(dense), atol=2e-6)


def test_vertex_blocks_partition_the_mesh(face):
    from canrig_jax.canrig._layout import vertex_blocks

    blocks = vertex_blocks(face[0], 48)
    assert blocks.shape[1] <= 48
    flat = blocks[blocks >= 0]
    assert np.array_equal(np.sort(flat), np.arange(len(face[0])))
    extent = [np.ptp(face[0][b[b >= 0]], axis=0).max() for b in blocks]
    assert np.median(extent) < 2.0  # compact blocks (cm, on an 18 cm wide face)


def test_influence_reach_bounds_every_non_zero_clamped_mask(neural_rig, placed):
    """The block-sparse path picks handles by distance alone: every handle with a non-zero
    clamped mask on a block's vertex lies within its reach of that block, and the reach is
    tight (the mask just inside it, 1 % short, is still above the clamp)."""
    from canrig_jax.canrig import influence_mask, influence_reach

    clamp = neural_rig.model.clamp
    rng = np.random.default_rng(2)
    h = placed.n_handles
    radius = rng.uniform(0.3, 4.0, h).astype(np.float32)
    falloff = rng.uniform(0.5, 8.0, h).astype(np.float32)
    reach = influence_reach(radius, falloff, clamp)
    distance = np.asarray(placed.distance)
    mask = np.asarray(influence_mask(distance, radius, falloff, clamp))
    assert np.all(distance[mask > 0] <= np.broadcast_to(reach, mask.shape)[mask > 0])
    # per block: the handles within reach of the block's nearest vertex include all
    # handles with a non-zero mask on any of its vertices
    blocks = np.asarray(neural_rig.blocks)
    padded = np.concatenate([mask, np.zeros((1, h), mask.dtype)])
    influencing = padded[blocks].max(axis=1) > 0  # (B, H)
    within = placed.block_distance <= reach[None, :]
    assert np.all(within[influencing])
    if clamp > 0:
        inside = np.asarray(
            influence_mask(reach[None, :] * 0.99 - 0.011, radius, falloff, clamp)
        )  # reach minus its margins and 1 %
        assert np.all(inside >= clamp)
    else:
        assert np.all(np.isinf(reach))


def test_bridge_reaches_separate_parts_from_skin_handles(data_dir, face):
    """On the face plus the eyelashes (separate pieces of mesh), a skin handle reaches the
    lashes only with bridge=True, no nearer than in a straight line, while its distances on
    the skin stay those of the plain edge graph."""
    from canrig_jax.data import load_ict
    from canrig_jax.mesh import edge_graph, weighted_geodesic_distance

    head = load_ict(data_dir, parts=["Face", "Eyelashes left", "Eyelashes right"])
    neutral, faces = np.asarray(head.neutral, np.float32), np.asarray(head.faces)
    n_face = head.part_vertex_range[0][1]
    model = CANRig(face[0], key=jax.random.PRNGKey(0))  # any model: only distances are read
    rig = NeuralRig(model, neutral, faces, bridge=True)
    index = np.random.default_rng(1).choice(n_face, 8, replace=False)
    near = np.asarray(rig.handles(index).distance)  # (V, H)
    far = weighted_geodesic_distance(edge_graph(neutral, faces), index).T
    assert np.isinf(far[n_face:]).all() and np.isfinite(near[n_face:]).all()
    np.testing.assert_array_equal(near[:n_face], far[:n_face])
    straight = np.linalg.norm(neutral[n_face:, None] - neutral[index][None], axis=-1)
    assert (near[n_face:] >= straight - 1e-4).all()
