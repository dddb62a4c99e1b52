"""RigAnyFace on real ICT heads: ground truth, model invariants, rig generation, glTF,
penetration metric, training and resuming, bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from canrig_jax.autorig import (
    RigAnyFaceNetwork,
    RigAnyFaceTrainOptions,
    load_riganyface,
    train_riganyface,
    training_set,
)
from canrig_jax.autorig._data import (
    PoseSet,
    head_rig,
    make_head,
    pose_displacements,
    quartic_pose_set,
)
from canrig_jax.autorig._diffusion import spectral_diffusion, spectral_diffusion_and_gradient
from canrig_jax.autorig._metrics import (
    inner_outside,
    outside_fraction,
    penetration,
    penetration_free_set,
    winding_numbers,
)
from canrig_jax.autorig._model import RigAnyFace
from canrig_jax.autorig._rig import pad_to_bucket, rig_from_poses
from canrig_jax.autorig._train import head_inputs
from canrig_jax.data import INNER_PARTS, load_ict
from canrig_jax.rig import evaluate, export_gltf, load_gltf_rig


@pytest.fixture(scope="module")
def ict_head(data_dir):
    return load_ict(data_dir, parts=None)


@pytest.fixture(scope="module")
def poses(ict_quartic):
    return quartic_pose_set(ict_quartic)


@pytest.fixture(scope="module")
def head_displacements(ict_quartic, ict_head, poses):
    return pose_displacements(head_rig(ict_quartic, ict_head), poses)


@pytest.fixture(scope="module")
def heads(ict_head, head_displacements, data_dir):
    rng = np.random.default_rng(3)
    return [
        make_head(ict_head, head_displacements, rng.standard_normal(100), topology, name=topology)
        for topology in ("decimate_600", "subdivide_300")
    ]


@pytest.fixture(scope="module")
def head_operators(heads):
    """(unit-sphere vertices, operators with 64 eigenpairs) of the decimated head."""
    unit, operators, _, _ = head_inputs(heads[0].vertices, heads[0].faces, k=64, cache=False)
    return unit, operators


@pytest.fixture(scope="module")
def small_model(poses):
    return RigAnyFace(
        poses.n_basis, width=8, global_size=4, global_width=8, key=jax.random.PRNGKey(0)
    )


# -- ground truth -------------------------------------------------------------------------------


def test_pose_set_is_singles_then_the_largest_correctives(poses, ict_quartic):
    assert poses.n_poses == 96 and poses.n_basis == 53
    vectors = poses.vectors()
    np.testing.assert_array_equal(vectors[:53], np.eye(53))
    orders = vectors[53:].sum(axis=1)
    assert (orders == 2).sum() == 25 and (orders == 3).sum() == 12 and (orders == 4).sum() == 6
    # the chosen pairs are the 25 largest order-2 correctives
    table = ict_quartic.corrective(2)
    size = np.linalg.norm(np.asarray(table.deltas), axis=-1).sum(axis=1)
    threshold = np.sort(size)[-25]
    chosen = {tuple(c) for c in poses.combinations[53:] if len(c) == 2}
    for row, indices in enumerate(np.asarray(table.indices)):
        assert (tuple(indices) in chosen) == (size[row] >= threshold)
    assert PoseSet.from_dict(poses.to_dict()) == poses


def test_combination_ground_truth_is_deltas_plus_every_contained_corrective(
    ict_quartic, ict_head, head_displacements, poses
):
    p = next(i for i, c in enumerate(poses.combinations) if len(c) == 4)
    combo = set(poses.combinations[p])
    expected = np.asarray(ict_head.deltas)[list(combo)].sum(axis=0).astype(np.float64)
    for table in ict_quartic.correctives:
        dense = table.to_dense(ict_quartic.n_vertices)
        for row, indices in enumerate(np.asarray(table.indices)):
            if set(indices.tolist()) <= combo:
                expected[: ict_quartic.n_vertices] += dense[row]
    np.testing.assert_allclose(head_displacements[p], expected, atol=2e-5)
    # expressions move only the face and the parts they drive; the combination moves the face
    assert np.abs(head_displacements[p][: ict_quartic.n_vertices]).max() > 0.5


def test_remeshed_heads_carry_the_ground_truth_and_the_parts(heads, ict_head):
    for head in heads:
        assert head.displacements.shape == (96, head.n_vertices, 3)
        # every vertex of a part lies near that part's surface: teeth vertices near the
        # original teeth of the same identity
        teeth = ict_head.part_names.index("Teeth")
        assert (head.parts == teeth).sum() > 20
        # jaw-driven lower teeth move with jawOpen; the skull does not
        jaw = ict_head.names.index("jawOpen")
        moved = np.linalg.norm(head.displacements[jaw], axis=1)
        assert moved[head.parts == teeth].max() > 0.5
        skull = ict_head.part_names.index("Head and Neck")
        assert np.median(moved[head.parts == skull]) < 0.05
    # the subdivided head keeps its coarse vertices: their rows equal a coarse carry
    assert heads[1].n_vertices > 3 * 300


@pytest.mark.slow
def test_deformation_transfer_baseline_follows_the_ground_truth(
    ict_quartic, ict_head, head_displacements, poses, heads
):
    from canrig_jax.autorig import transfer_poses
    from canrig_jax.autorig._data import AutorigDataset

    dataset = AutorigDataset(poses, ict_head, head_displacements, [], {})
    head = heads[0]
    transferred = transfer_poses(dataset, head)
    assert transferred.shape == head.displacements.shape
    error = np.linalg.norm(transferred - head.displacements, axis=-1).mean()
    motion = np.linalg.norm(head.displacements, axis=-1).mean()
    assert error < 0.5 * motion, (error, motion)


# -- model ----------------------------------------------------------------------------------------


@pytest.mark.slow
def test_padding_does_not_change_the_prediction(small_model, head_operators, poses):
    unit, operators = head_operators
    vectors = jnp.asarray(poses.vectors()[:7])
    plain = small_model(vectors, jnp.asarray(unit), operators)
    padded_ops = pad_to_bucket(operators, 512)
    padded_unit = jnp.zeros((padded_ops.n_vertices, 3)).at[: unit.shape[0]].set(unit)
    padded = small_model(vectors, padded_unit, padded_ops)
    np.testing.assert_allclose(padded[:, : unit.shape[0]], plain, atol=1e-6)
    assert np.all(np.asarray(padded[:, unit.shape[0] :]) == 0)


@pytest.mark.slow
def test_all_poses_in_one_call_equal_one_pose_at_a_time(small_model, head_operators, poses):
    """The batched path (pose-independent work done once) and the chunked path are the
    per-pose function."""
    unit, operators = head_operators
    vectors = jnp.asarray(poses.vectors()[50:58])
    batched = small_model(vectors, jnp.asarray(unit), operators)
    single = jnp.concatenate(
        [small_model(vectors[i : i + 1], jnp.asarray(unit), operators) for i in range(8)]
    )
    np.testing.assert_allclose(batched, single, rtol=1e-5, atol=1e-7)
    # in chunks of 3 poses (lax.map over 3 chunks, the last one padded)
    chunked = small_model(vectors, jnp.asarray(unit), operators, pose_chunk=3)
    np.testing.assert_allclose(chunked, batched, rtol=1e-5, atol=1e-7)
    # and equals feeding the first conditional block an explicitly broadcast input
    x = (
        jax.vmap(small_model.first)(jnp.concatenate([unit, operators.frames[:, 2]], axis=1))
        * operators.vertex_mask[:, None]
    )
    for block in small_model.shared:
        x = block(x, operators)
    code = small_model.global_code(jnp.asarray(unit), operators)
    conditions = jnp.concatenate([vectors, jnp.broadcast_to(code, (8, code.shape[0]))], axis=1)
    y = jnp.broadcast_to(x[:, None], (x.shape[0], 8, x.shape[1]))
    for block in small_model.conditional:
        y = block(y, conditions, operators)
    reference = jax.vmap(jax.vmap(small_model.last))(y) * operators.vertex_mask[:, None, None]
    np.testing.assert_allclose(
        batched, jnp.swapaxes(reference, 0, 1) * small_model.output_scale, rtol=1e-5, atol=1e-7
    )


@pytest.mark.slow
def test_only_the_global_encoder_carries_information_across_components(
    poses, heads, head_operators, ict_head
):
    """Diffusion cannot cross disconnected parts; G_0 can (the paper's motivation)."""
    head = heads[0]
    unit, operators = head_operators
    eyeball = head.parts == ict_head.part_names.index("Eyeball left")
    face = head.parts == ict_head.part_names.index("Face")
    moved = unit.copy()
    moved[eyeball] += np.array([0.0, 0.0, 0.05], np.float32)  # translate the eyeball only
    vectors = jnp.asarray(poses.vectors()[:3])
    key = jax.random.PRNGKey(1)
    for global_size, crosses in ((0, False), (4, True)):
        model = RigAnyFace(poses.n_basis, width=8, global_size=global_size, global_width=8, key=key)
        a = np.asarray(model(vectors, jnp.asarray(unit), operators))[:, face]
        b = np.asarray(model(vectors, jnp.asarray(moved), operators))[:, face]
        change = np.abs(a - b).max() / np.abs(a).max()
        if crosses:
            assert change > 1e-6, change  # float32 round-off is ~1e-7; without G_0: exactly 0
        else:
            assert change == 0.0, change


@pytest.mark.slow
def test_hybrid_model_diffuses_implicitly_once_per_head_and_spectrally_per_pose(
    poses, head_operators
):
    """``stem_method="implicit"``: the global encoder and the stem use implicit diffusion
    (eq. (1)), the per-pose blocks stay spectral. Implicit diffusion keeps every vertex's
    own detail (at time 0 it is the identity; the 64 eigenpairs are a low-pass projection)."""
    unit, operators = head_operators
    kwargs = dict(width=8, global_size=4, global_width=8, key=jax.random.PRNGKey(2))
    hybrid = RigAnyFace(poses.n_basis, stem_method="implicit", **kwargs)
    spectral = RigAnyFace(poses.n_basis, **kwargs)
    assert [b.diffusion.method for b in hybrid.shared] == ["implicit"] * 2
    assert [b.diffusion.method for b in hybrid.encoder.blocks] == ["implicit"] * 2
    assert [c.block.diffusion.method for c in hybrid.conditional] == ["spectral"] * 2
    features = jnp.asarray(np.random.default_rng(0).normal(size=(unit.shape[0], 8)), jnp.float32)
    np.testing.assert_allclose(hybrid.shared[0].diffusion(features, operators), features, atol=1e-5)
    low_pass = spectral.shared[0].diffusion(features, operators)
    assert np.abs(np.asarray(low_pass) - np.asarray(features)).max() > 0.1
    vectors = jnp.asarray(poses.vectors()[:3])
    a = np.asarray(hybrid(vectors, jnp.asarray(unit), operators))
    b = np.asarray(spectral(vectors, jnp.asarray(unit), operators))
    assert np.isfinite(a).all() and np.abs(a - b).max() > 1e-5
    with pytest.raises(ValueError, match="method"):
        RigAnyFace(poses.n_basis, stem_method="explicit", **kwargs)


def test_spectral_gradient_shortcut_equals_the_sparse_gradient_of_the_diffusion(head_operators):
    unit, operators = head_operators
    features = jnp.asarray(
        np.random.default_rng(0).standard_normal((unit.shape[0], 5, 4)), jnp.float32
    )
    times = jnp.asarray([0.0, 1e-3, 1e-2, 1e-1], jnp.float32)
    diffused, gx, gy = spectral_diffusion_and_gradient(features, times, operators)
    np.testing.assert_allclose(diffused, spectral_diffusion(features, times, operators), atol=1e-5)
    scale = float(jnp.abs(gx).max())
    np.testing.assert_allclose(gx, operators.gradient_x(diffused), atol=1e-4 * scale)
    np.testing.assert_allclose(gy, operators.gradient_y(diffused), atol=1e-4 * scale)


# -- rig generation and export --------------------------------------------------------------------


@pytest.mark.slow
def test_generated_rig_reproduces_every_predicted_pose(small_model, poses, heads):
    head = heads[0]
    generated = RigAnyFaceNetwork((small_model, poses)).generate(
        head.vertices * 3.0, head.faces, k=64
    )
    rig = generated.rig
    assert rig.names == poses.basis_names and rig.n_vertices == head.n_vertices
    posed = jax.vmap(lambda w: evaluate(rig, w))(jnp.asarray(poses.vectors()))
    np.testing.assert_allclose(
        np.asarray(posed) - np.asarray(rig.neutral)[None], generated.displacements, atol=1e-4
    )
    # units follow the input: scaling the head scales the displacements
    unit = RigAnyFaceNetwork((small_model, poses)).generate(head.vertices, head.faces, k=64)
    np.testing.assert_allclose(
        generated.displacements, 3.0 * unit.displacements, rtol=1e-3, atol=1e-5
    )


def test_gltf_export_reloads_with_trimesh_to_the_same_rig(heads, poses, tmp_path):
    head = heads[0]
    rig = rig_from_poses(head.vertices, head.faces, head.displacements, poses)
    path = export_gltf(rig, tmp_path / "rig.glb")
    mesh = trimesh.load(path, force="mesh", process=False)
    np.testing.assert_array_equal(mesh.vertices, rig.neutral)
    np.testing.assert_array_equal(mesh.faces, rig.faces)
    back = load_gltf_rig(path)
    assert back.names == rig.names
    np.testing.assert_array_equal(back.deltas, rig.deltas)
    assert [c.order for c in back.correctives] == [2, 3, 4]
    for a, b in zip(back.correctives, rig.correctives, strict=True):
        np.testing.assert_array_equal(a.indices, b.indices)
        np.testing.assert_allclose(a.to_dense(rig.n_vertices), b.to_dense(rig.n_vertices), atol=0)
    # and the reloaded rig poses exactly like the ground truth
    p = 60
    posed = evaluate(back, jnp.asarray(poses.vectors()[p])) - back.neutral
    np.testing.assert_allclose(posed, head.displacements[p], atol=1e-5)


# -- penetration ----------------------------------------------------------------------------------


def test_winding_numbers_of_a_closed_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=3)
    points = np.array([[0, 0, 0], [0.5, 0.2, -0.1], [1.5, 0, 0], [0, -3, 0.2]], np.float32)
    w = np.asarray(winding_numbers(jnp.asarray(points), jnp.asarray(sphere.triangles, jnp.float32)))
    np.testing.assert_allclose(w, [1, 1, 0, 0], atol=1e-4)


def test_inner_parts_are_inside_the_skin_and_pushing_them_out_is_detected(heads, ict_head):
    head = heads[0]
    zero = np.zeros((1, head.n_vertices, 3), np.float32)
    at_rest = penetration(head, zero, ict_head.part_names)
    assert at_rest < 0.15  # the eyeballs' fronts show through the eye openings
    teeth = head.parts == ict_head.part_names.index("Teeth")
    push = zero.copy()
    push[0, teeth, 2] = 5.0  # 5 cm forward, through the lips
    inner = np.isin(head.parts, [ict_head.part_names.index(p) for p in INNER_PARTS])
    expected = at_rest + teeth.sum() / inner.sum() * 0.9
    assert penetration(head, push, ict_head.part_names) > expected
    with pytest.raises(ValueError, match="inner"):
        outside_fraction(
            head.vertices,
            head.faces,
            np.zeros(head.n_vertices, bool),
            np.ones(len(head.faces), bool),
        )


@pytest.mark.slow
def test_penetration_free_set_scores_the_truth_zero_and_catches_a_push(heads, ict_head):
    head = heads[0]
    names = ict_head.part_names
    poses, vertices = penetration_free_set(head, names)
    truth = inner_outside(head, head.displacements, names)
    rest = inner_outside(head, np.zeros((1, head.n_vertices, 3)), names)[0]
    # the selection: inner vertices inside at rest, poses whose truth pushes none of them out
    np.testing.assert_array_equal(vertices, ~rest)
    assert 0 < poses.size < head.displacements.shape[0] or poses.size == truth.shape[0]
    assert not truth[poses][:, vertices].any()
    assert truth[np.setdiff1d(np.arange(truth.shape[0]), poses)][:, vertices].any(axis=1).all()
    # a prediction that pushes the teeth 5 cm forward on the selected poses is caught
    teeth = head.parts == names.index("Teeth")
    inner = np.isin(head.parts, [names.index(p) for p in INNER_PARTS])
    pushed = head.displacements.copy()
    pushed[:, teeth, 2] += 5.0
    outside = inner_outside(head, pushed, names)[poses][:, vertices]
    teeth_inner = teeth[inner][vertices]
    assert outside[:, teeth_inner].mean() > 0.9 and outside[:, ~teeth_inner].mean() < 0.05
    # the plain metric is the mean of inner_outside
    assert penetration(head, head.displacements, names) == pytest.approx(truth.mean())
    with pytest.raises(ValueError, match="threshold"):
        penetration_free_set(head, names, threshold=1.5)


# -- training -------------------------------------------------------------------------------------


@pytest.mark.slow
def test_training_lowers_the_error_and_resumes_to_the_same_model(heads, poses, tmp_path):
    data = training_set(heads[:1], poses, k=64, progress=False)
    options = RigAnyFaceTrainOptions(
        width=8,
        global_size=4,
        global_width=8,
        k=64,
        steps=24,
        warmup_steps=2,
        learning_rate=3e-3,
        poses_per_step=4,
        heads_per_step=1,
        checkpoint_every=8,
        log_every=1,
    )
    full = train_riganyface(data, poses, options, checkpoint=tmp_path / "a.eqx", progress=False)
    first, last = full.history[0]["error_mm"], np.mean([h["error_mm"] for h in full.history[-4:]])
    assert last < 0.8 * first, (first, last)
    train_riganyface(
        data, poses, options, checkpoint=tmp_path / "b.eqx", progress=False, stop_after=10
    )
    resumed = train_riganyface(data, poses, options, checkpoint=tmp_path / "b.eqx", progress=False)
    assert resumed.step == full.step == 24
    a, _, _ = load_riganyface(tmp_path / "a.eqx")
    b, _, _ = load_riganyface(tmp_path / "b.eqx")
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="different options"):
        train_riganyface(
            data,
            poses,
            RigAnyFaceTrainOptions(**{**options.to_dict(), "learning_rate": 1e-3}),
            checkpoint=tmp_path / "a.eqx",
            progress=False,
        )


# -- bad input ------------------------------------------------------------------------------------


def test_bad_input_raises_naming_the_argument(small_model, poses, heads, head_operators):
    head = heads[0]
    with pytest.raises(ValueError, match="faces"):
        RigAnyFaceNetwork((small_model, poses)).generate(head.vertices, np.zeros((0, 3), np.int32))
    bad = head.vertices.copy()
    bad[5] = np.nan
    with pytest.raises(ValueError, match="vertices"):
        RigAnyFaceNetwork((small_model, poses)).generate(bad, head.faces)
    with pytest.raises(ValueError, match="memory_budget"):
        RigAnyFaceNetwork((small_model, poses)).generate(
            head.vertices, head.faces, memory_budget=1 << 20
        )
    unit, operators = head_operators
    with pytest.raises(ValueError, match="poses"):
        small_model(jnp.ones((3, 52)), jnp.asarray(unit), operators)
    with pytest.raises(ValueError, match="pose_chunk"):
        RigAnyFaceNetwork((small_model, poses)).generate(head.vertices, head.faces, pose_chunk=0)
    other = PoseSet(poses.basis_names[:52], tuple((i,) for i in range(52)))
    with pytest.raises(ValueError, match="poses"):
        RigAnyFaceNetwork((small_model, other)).generate(head.vertices, head.faces, k=16)
    with pytest.raises(ValueError, match="combinations"):
        PoseSet(poses.basis_names, ((1,), (0,)))
