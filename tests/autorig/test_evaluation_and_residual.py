"""Issue 19: the DT + learned residual model, the static-vertex loss term, the evaluation's
pose and vertex classes, the shared ARKit shapes of ICT and MakeHuman, and fitting ICT's
landmarks to a new head."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.autorig import (
    RigAnyFaceNetwork,
    RigAnyFaceTrainOptions,
    TransferResidual,
    load_makehuman,
    load_riganyface,
    train_riganyface,
    training_set,
)
from canrig_jax.autorig._data import PoseSet
from canrig_jax.autorig._evaluation import (
    STATIC_MM,
    class_errors,
    pose_classes,
    sculpted_shape_errors,
    sculpted_target_errors,
    shared_shape_matrix,
    static_mask,
    worst_poses,
)
from canrig_jax.autorig._model import RigAnyFace
from canrig_jax.autorig._train import STATIC_CM, head_inputs, static_vertex_error
from canrig_jax.data import load_ict
from canrig_jax.mesh import decimate, fit_landmarks


@pytest.fixture(scope="module")
def ict_head(data_dir):
    return load_ict(data_dir, parts=None)


@pytest.fixture(scope="module")
def small_head(ict_head):
    """The generic ICT head decimated to ~500 vertices, with its unit-sphere operators."""
    mesh = decimate(ict_head.neutral, ict_head.faces, 500)
    unit, operators, _, scale = head_inputs(mesh.vertices, mesh.faces, k=32, cache=False)
    return mesh, unit, operators, scale


@pytest.fixture(scope="module")
def tiny_poses():
    names = ("jawOpen", "mouthSmile_L", "eyeBlink_L", "browInnerUp_L")
    return PoseSet(names, ((0,), (1,), (2,), (3,), (0, 1), (1, 2, 3)))


def residual_model(poses, key=0):
    return RigAnyFace(
        poses.n_basis,
        width=8,
        global_size=4,
        global_width=8,
        residual=True,
        output_scale=0.01,
        key=jax.random.PRNGKey(key),
    )


@pytest.mark.slow  # 12 s: builds operators and compiles the residual network
def test_residual_model_at_initialisation_returns_the_base_exactly(small_head, tiny_poses):
    mesh, unit, operators, scale = small_head
    rng = np.random.default_rng(0)
    base = rng.normal(0, 0.01, (tiny_poses.n_poses, unit.shape[0], 3)).astype(np.float32)
    model = residual_model(tiny_poses)
    out = model(jnp.asarray(tiny_poses.vectors()), jnp.asarray(unit), operators, base=base)
    np.testing.assert_array_equal(np.asarray(out), base)
    chunked = model(
        jnp.asarray(tiny_poses.vectors()), jnp.asarray(unit), operators, base=base, pose_chunk=4
    )
    np.testing.assert_array_equal(np.asarray(chunked), base)
    # through TransferResidual.generate, in the head's units (cm): the rig is deformation transfer
    base_cm = base * scale
    generated = TransferResidual((model, tiny_poses)).generate(
        mesh.vertices, mesh.faces, k=32, operators=operators, base=base_cm
    )
    np.testing.assert_allclose(generated.displacements, base_cm, rtol=1e-5, atol=1e-7)
    # a plain model of the same size does move the head (the zero start is the residual's)
    plain = RigAnyFace(
        tiny_poses.n_basis, width=8, global_size=4, global_width=8, key=jax.random.PRNGKey(0)
    )
    moved = plain(jnp.asarray(tiny_poses.vectors()), jnp.asarray(unit), operators)
    assert float(jnp.abs(moved).max()) > 0


def test_residual_model_refuses_a_missing_or_misshaped_base(small_head, tiny_poses):
    mesh, unit, operators, _ = small_head
    model = residual_model(tiny_poses)
    with pytest.raises(ValueError, match="base"):
        TransferResidual((model, tiny_poses)).generate(
            mesh.vertices, mesh.faces, k=32, operators=operators
        )
    with pytest.raises(ValueError, match="base"):
        TransferResidual((model, tiny_poses)).generate(
            mesh.vertices,
            mesh.faces,
            k=32,
            operators=operators,
            base=np.zeros((2, mesh.vertices.shape[0], 3)),
        )
    plain = RigAnyFace(tiny_poses.n_basis, width=8, global_size=0, key=jax.random.PRNGKey(1))
    with pytest.raises(ValueError, match="base"):
        RigAnyFaceNetwork((plain, tiny_poses)).generate(
            mesh.vertices,
            mesh.faces,
            k=32,
            operators=operators,
            base=np.zeros((tiny_poses.n_poses, mesh.vertices.shape[0], 3)),
        )


@pytest.mark.slow
def test_gated_residual_keeps_what_the_base_leaves_still_exactly_still(small_head, tiny_poses):
    """With residual_gate tau the correction vanishes where the base is zero and is (almost)
    the ungated one where the base moves by many tau; tau without residual is refused."""
    mesh, unit, operators, _ = small_head
    tau = 1e-4
    gated, plain = (
        eqx.tree_at(
            lambda m: (m.last.weight, m.last.bias),
            RigAnyFace(
                tiny_poses.n_basis, width=8, global_size=4, global_width=8, residual=True,
                residual_gate=gate, output_scale=0.01, key=jax.random.PRNGKey(2),
            ),
            (jnp.full((3, 8), 0.3), jnp.full((3,), 0.1)),
        )  # a nonzero last layer: the correction is no longer zero
        for gate in (tau, 0.0)
    )  # fmt: skip
    rng = np.random.default_rng(1)
    base = rng.normal(0, 0.05, (tiny_poses.n_poses, unit.shape[0], 3)).astype(np.float32)
    still = rng.random((tiny_poses.n_poses, unit.shape[0])) < 0.5
    base[still] = 0.0
    vectors, vertices = jnp.asarray(tiny_poses.vectors()), jnp.asarray(unit)
    out = np.asarray(gated(vectors, vertices, operators, base=base))
    ungated = np.asarray(plain(vectors, vertices, operators, base=base))
    np.testing.assert_array_equal(out[still], 0.0)
    assert np.abs(ungated[still]).max() > 1e-3  # the ungated correction does move them
    large = np.linalg.norm(base, axis=-1) > 100 * tau  # gate > 0.9999 there
    np.testing.assert_allclose(out[large], ungated[large], rtol=1e-3, atol=1e-6)
    chunked = gated(vectors, vertices, operators, base=base, pose_chunk=4)
    np.testing.assert_allclose(np.asarray(chunked), out, rtol=1e-5, atol=1e-7)
    with pytest.raises(ValueError, match="residual_gate"):
        RigAnyFace(tiny_poses.n_basis, width=8, residual_gate=tau, key=jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="residual_gate"):
        RigAnyFaceTrainOptions(residual_gate=tau)


def test_static_vertex_term_is_zero_on_a_still_head_and_measures_drift():
    rng = np.random.default_rng(1)
    truth = rng.normal(size=(3, 50, 3)).astype(np.float32)
    truth[:, :20] = 0.0  # 20 static vertices in every pose
    mask = np.ones(50, np.float32)
    threshold = 1e-3
    still = jnp.asarray(truth)  # a perfect prediction: static vertices predicted still
    assert float(static_vertex_error(still, jnp.asarray(truth), mask, threshold)) == 0.0
    zero = jnp.zeros_like(still)  # a head that does not move at all
    assert float(static_vertex_error(zero, jnp.asarray(truth), mask, threshold)) == 0.0
    drift = np.array(truth)
    drift[:, :20] = [0.0, 0.3, 0.4]  # static vertices drift by 0.5
    value = float(static_vertex_error(jnp.asarray(drift), jnp.asarray(truth), mask, threshold))
    assert value == pytest.approx(0.5, rel=1e-6)
    # padding (mask 0) does not count; the gradient is finite at a still prediction
    masked = mask.copy()
    masked[:10] = 0
    assert float(
        static_vertex_error(jnp.asarray(drift), jnp.asarray(truth), masked, threshold)
    ) == pytest.approx(0.5, rel=1e-6)
    grad = jax.grad(lambda p: static_vertex_error(p, jnp.asarray(truth), mask, threshold))(zero)
    assert np.all(np.isfinite(np.asarray(grad)))


def test_evaluation_classes_partition_the_poses_and_the_vertices(tiny_poses):
    classes = pose_classes(tiny_poses)
    np.testing.assert_array_equal(
        np.sort(np.concatenate(list(classes.values()))), np.arange(tiny_poses.n_poses)
    )
    assert set(classes["single"]) == set(range(tiny_poses.n_basis))
    rng = np.random.default_rng(2)
    truth, predicted = [], []
    for n in (40, 70):  # two heads of different sizes
        t = rng.normal(0, 0.05, (tiny_poses.n_poses, n, 3))
        t[:, : n // 3] *= 1e-5  # below 0.01 mm
        truth.append(t)
        predicted.append(t + rng.normal(0, 0.01, t.shape))
    stats = class_errors(predicted, truth, tiny_poses)
    for s in stats.values():
        f = s["static_fraction"]
        assert 0 < f < 1
        assert f * s["static_mae_mm"] + (1 - f) * s["moving_mae_mm"] == pytest.approx(
            s["mae_mm"], rel=1e-9
        )
        assert s["q95_mm"] > s["mae_mm"] > 0
    assert static_mask(truth[0]).shape == truth[0].shape[:2]
    assert static_mask(np.full((1, 1, 3), STATIC_MM / 10 / 2)).all()  # 0.0087 mm: static
    # no motion: the error is the displacement itself, and static pairs score below 0.01 mm
    zeros = class_errors([np.zeros_like(t) for t in truth], truth, tiny_poses)
    assert zeros["single"]["static_mae_mm"] < STATIC_MM
    worst = worst_poses(predicted, truth, tiny_poses, 3)
    assert [w["mae_mm"] for w in worst] == sorted((w["mae_mm"] for w in worst), reverse=True)
    assert len({w["pose"] for w in worst}) == 3


@pytest.mark.bad_input
def test_shared_shapes_sum_ict_split_halves(ict_head, data_dir):
    mh = load_makehuman(data_dir)
    target_index, matrix = shared_shape_matrix(ict_head.names, mh.names)
    kept = [mh.names[i] for i in target_index]
    assert len(kept) == 51 and "tongueOut" not in kept
    names = list(ict_head.names)
    for arkit, halves in (("browInnerUp", 2), ("cheekPuff", 2), ("jawOpen", 1)):
        row = matrix[kept.index(arkit)]
        assert row.sum() == halves
    row = matrix[kept.index("browInnerUp")]
    assert row[names.index("browInnerUp_L")] == row[names.index("browInnerUp_R")] == 1
    shared = np.einsum("sk,kvd->svd", matrix, ict_head.deltas)
    np.testing.assert_allclose(
        shared[kept.index("cheekPuff")],
        ict_head.deltas[names.index("cheekPuff_L")] + ict_head.deltas[names.index("cheekPuff_R")],
    )
    eye = kept.index("eyeBlinkLeft")
    np.testing.assert_array_equal(shared[eye], ict_head.deltas[names.index("eyeBlink_L")])
    # the MakeHuman head is in centimetres after loading (a head's size, not decimetres)
    assert 20 < np.ptp(mh.neutral[:, 1]) < 40
    # metrics: perfect prediction 0, no motion has amplitude ratio 0
    truth = mh.deltas[target_index[:3]]
    perfect = sculpted_target_errors(truth, truth, mh.skin)
    assert perfect["skin_mae_mm"] == 0 and perfect["amplitude_ratio_median"] == pytest.approx(1)
    none = sculpted_target_errors(np.zeros_like(truth), truth, mh.skin)
    assert none["amplitude_ratio_median"] == 0 and none["active_mae_mm"] > 0.5
    # per shape: half the motion is half the amplitude and peak, its error the other half's
    # size; the shapes' skin MAEs average to the overall one (same skin in every shape)
    half = sculpted_shape_errors(0.5 * truth, truth, mh.skin)
    np.testing.assert_allclose(half["amplitude_ratio"], 0.5, rtol=1e-9)
    np.testing.assert_allclose(half["peak_mm"], 0.5 * half["target_peak_mm"], rtol=1e-9)
    lengths = np.linalg.norm(truth[:, mh.skin], axis=-1) * 10.0
    np.testing.assert_allclose(half["skin_mae_mm"], 0.5 * lengths.mean(axis=1), rtol=1e-6)
    mixed = truth * np.array([0.0, 1.0, 2.0])[:, None, None]
    np.testing.assert_allclose(
        sculpted_shape_errors(mixed, truth, mh.skin)["skin_mae_mm"].mean(),
        sculpted_target_errors(mixed, truth, mh.skin)["skin_mae_mm"],
        rtol=1e-9,
    )
    with pytest.raises(ValueError, match="predicted, truth"):
        sculpted_shape_errors(truth[:2], truth, mh.skin)


@pytest.mark.slow  # 12-21 s; the default run stays under 10 min on 2 cores
def test_fitted_landmarks_recover_a_known_similarity(ict_head):
    """The ICT face fitted to a scaled, rotated, shifted and remeshed copy of the ICT head:
    the similarity is recovered and the landmarks land where the true ones are."""
    angle = np.deg2rad(6.0)
    rotation = np.array(
        [[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]]
    )
    move = lambda x: 0.9 * x @ rotation.T + np.array([1.0, -2.0, 0.5])  # noqa: E731
    remeshed = decimate(ict_head.neutral, ict_head.faces, 3000)
    target = move(remeshed.vertices)
    face = np.zeros(ict_head.n_vertices, bool)
    face[:9409] = True
    landmarks, fit = fit_landmarks(
        ict_head.neutral, ict_head.landmarks, face, target, remeshed.faces
    )
    assert fit.scale == pytest.approx(0.9, rel=0.01)
    np.testing.assert_allclose(fit.rotation, rotation, atol=0.01)
    true_positions = move(ict_head.neutral[ict_head.landmarks])
    distance = np.linalg.norm(target[landmarks] - true_positions, axis=1)
    spacing = np.median(np.linalg.norm(np.diff(target[remeshed.faces], axis=1), axis=-1))
    assert np.median(distance) < spacing  # the nearest remeshed vertex, about
    # the same head in metres is refused, naming the argument
    with pytest.raises(ValueError, match="target_vertices"):
        fit_landmarks(ict_head.neutral, ict_head.landmarks, face, target / 100, remeshed.faces)
    # and the same head stored z up (a quarter turn about x) does not fit: refused
    z_up = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    with pytest.raises(ValueError, match="target_vertices"):
        fit_landmarks(
            ict_head.neutral, ict_head.landmarks, face, remeshed.vertices @ z_up.T, remeshed.faces
        )


@pytest.mark.slow
def test_residual_training_improves_on_its_base_and_resumes(small_head, tiny_poses, tmp_path):
    """A residual model trained on one head lowers the error of a biased base (the base
    here: ground truth scaled by 0.7 plus a constant drift of the static vertices)."""
    from canrig_jax.autorig._data import RiggedHead

    mesh, *_ = small_head
    rng = np.random.default_rng(4)
    n = mesh.vertices.shape[0]
    truth = np.zeros((tiny_poses.n_poses, n, 3), np.float32)
    moving = mesh.vertices[:, 1] < np.median(mesh.vertices[:, 1])
    truth[:, moving] = rng.normal(0, 0.1, (tiny_poses.n_poses, 1, 3))
    head = RiggedHead(
        "one", mesh.vertices, mesh.faces, truth, np.arange(10), np.zeros(n, np.int32),
        np.zeros(1), "decimate_500",
    )  # fmt: skip
    base = 0.7 * truth + 0.01
    data = training_set([head], tiny_poses, k=32, progress=False, base=[base])
    options = RigAnyFaceTrainOptions(
        width=8, global_size=4, global_width=8, k=32, steps=60, warmup_steps=2,
        learning_rate=1e-2, poses_per_step=4, heads_per_step=1, checkpoint_every=10,
        log_every=1, residual=True, loss="euclidean", static_weight=1.0,
    )  # fmt: skip
    full = train_riganyface(
        data, tiny_poses, options, checkpoint=tmp_path / "a.eqx", progress=False
    )
    first = full.history[0]["error_mm"]  # the base's error: the correction starts at zero
    last = np.mean([h["error_mm"] for h in full.history[-5:]])
    assert last < 0.8 * first, (first, last)
    train_riganyface(
        data, tiny_poses, options, checkpoint=tmp_path / "b.eqx", progress=False, stop_after=7
    )
    train_riganyface(data, tiny_poses, options, checkpoint=tmp_path / "b.eqx", progress=False)
    a, _, _ = load_riganyface(tmp_path / "a.eqx")
    b, _, _ = load_riganyface(tmp_path / "b.eqx")
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="data"):
        train_riganyface(
            training_set([head], tiny_poses, k=32, progress=False), tiny_poses, options
        )


def _one_head_and_small_model(mesh, truth, poses):
    """The training set of one head with ground truth ``truth`` (P, V, 3), and a small random
    model: what the loss tests evaluate ``batch_loss`` on."""
    from canrig_jax.autorig._data import RiggedHead

    n = mesh.vertices.shape[0]
    head = RiggedHead(
        "one", mesh.vertices, mesh.faces, truth, np.arange(10), np.zeros(n, np.int32),
        np.zeros(1), "decimate_500",
    )  # fmt: skip
    data = training_set([head], poses, k=32, progress=False)
    model = RigAnyFace(
        poses.n_basis, width=8, global_size=4, global_width=8, output_scale=0.05,
        key=jax.random.PRNGKey(1),
    )  # fmt: skip
    return data, model


@pytest.mark.slow
def test_static_term_adds_to_either_loss(small_head, tiny_poses):
    """static_weight adds the static-vertex error over the loss's scale to the squared loss as
    to the Euclidean one (it used to be dropped silently with loss="squared")."""
    from canrig_jax.autorig._train import batch_loss, mean_square_displacement

    mesh, *_ = small_head
    n = mesh.vertices.shape[0]
    truth = np.zeros((tiny_poses.n_poses, n, 3), np.float32)
    truth[:, mesh.vertices[:, 1] < np.median(mesh.vertices[:, 1])] = 0.2  # the rest is static
    data, model = _one_head_and_small_model(mesh, truth, tiny_poses)
    reference = jnp.asarray(mean_square_displacement(data))
    heads, poses = jnp.array([0]), jnp.array([[0, 1, 2]])
    predicted = model(
        data.poses[poses[0]], data.vertices[0], jax.tree.map(lambda x: x[0], data.operators)
    )
    static = static_vertex_error(
        predicted, data.displacements[0][poses[0]], data.operators.vertex_mask[0],
        STATIC_CM / data.scale[0],
    )  # fmt: skip
    assert static > 0  # a random model moves the static vertices
    for kind in ("squared", "euclidean"):
        without, _ = batch_loss(model, data, heads, poses, 1.0, reference, kind, 0.0)
        with_term, _ = batch_loss(model, data, heads, poses, 1.0, reference, kind, 2.0)
        np.testing.assert_allclose(
            with_term - without, 2.0 * static / jnp.sqrt(reference), rtol=1e-4
        )


@pytest.mark.slow  # 12-21 s; the default run stays under 10 min on 2 cores
def test_part_matching_on_makehuman_is_plausible_and_reported(ict_head, data_dir):
    """MakeHuman's eye proxies go to ICT's eyeballs of the same side, its teeth and tongue
    proxies to no eye part (the old area-first rule sent the teeth to the left eyeball)."""
    from canrig_jax.mesh import closest_point_correspondence, connected_components

    mh = load_makehuman(data_dir)
    face = np.zeros(ict_head.n_vertices, bool)
    face[:9409] = True
    landmarks, _ = fit_landmarks(
        ict_head.neutral, ict_head.landmarks, face, mh.neutral, mh.faces, target_region=mh.skin
    )
    correspondence = closest_point_correspondence(
        ict_head.neutral, ict_head.faces, mh.neutral, mh.faces, ict_head.landmarks, landmarks
    )
    match = correspondence.component_match
    source_labels = connected_components(ict_head.faces, ict_head.n_vertices)
    part_of = {}
    for i, (lo, hi) in enumerate(ict_head.part_vertex_range):
        for c in np.unique(source_labels[lo:hi]):
            part_of.setdefault(int(c), str(ict_head.part_names[i]))
    target_labels = mh.component_labels
    for label in np.unique(target_labels):
        matched = part_of[int(match[label])]
        x = mh.neutral[target_labels == label, 0].mean()
        if label == np.argmax(np.bincount(target_labels)):
            assert matched == "Face"
        elif np.sum(target_labels == label) == 72:  # the eye proxies
            assert matched == ("Eyeball left" if x > 0 else "Eyeball right")
        else:  # teeth and tongue proxies
            assert "Eye" not in matched, (label, matched)
    # a part far from anything on the source is refused, naming the argument
    far = np.array([[0.0, 70.0, -200.0], [1.0, 70.0, -200.0], [0.0, 71.0, -200.0]], np.float32)
    vertices = np.concatenate([mh.neutral, far])
    faces = np.concatenate(
        [mh.faces, [[len(mh.neutral), len(mh.neutral) + 1, len(mh.neutral) + 2]]]
    )
    with pytest.raises(ValueError, match="target_vertices"):
        closest_point_correspondence(
            ict_head.neutral, ict_head.faces, vertices, faces, ict_head.landmarks, landmarks
        )


@pytest.mark.bad_input
def test_anchor_modes_label_the_ict_parts_and_refuse_bad_input(ict_head):
    """``anchor_parts``: no labels per vertex; per part, ICT's connected components; with the
    skin per vertex, the largest component (face, head and neck, mouth and eye sockets:
    vertices 0..14061) -1 and the others unchanged. Bad modes and per-part anchoring without
    a threshold are refused, naming the argument."""
    from types import SimpleNamespace

    from canrig_jax.autorig import transfer_poses
    from canrig_jax.autorig._data import ANCHOR_MODES, anchor_parts
    from canrig_jax.mesh import connected_components

    assert ANCHOR_MODES == ("vertex", "part", "skin_vertex")
    assert anchor_parts(ict_head, "vertex") is None
    components = connected_components(ict_head.faces, ict_head.n_vertices)
    np.testing.assert_array_equal(anchor_parts(ict_head, "part"), components)
    skin_vertex = anchor_parts(ict_head, "skin_vertex")
    skin = skin_vertex == -1
    assert skin.sum() == 14062 and skin[:14062].all()
    np.testing.assert_array_equal(skin_vertex[~skin], components[~skin])
    assert len(np.unique(components[~skin])) > 50  # teeth, gums, eyes, lashes: each its own
    with pytest.raises(ValueError, match="^anchor:"):
        anchor_parts(ict_head, "face")
    source = SimpleNamespace(head=ict_head)
    with pytest.raises(ValueError, match="^anchor:"):
        transfer_poses(source, ict_head, anchor="part")  # no static_below
    with pytest.raises(ValueError, match="^anchor:"):
        transfer_poses(source, ict_head, static_below=1e-3, anchor="whole")


@pytest.mark.slow  # ~1 min: the ICT pose source, an ICP fit and three transfers
def test_transfer_poses_needs_only_the_head(data_dir):
    """Deformation transfer onto a held-out-like ICT identity given as a bare mesh (vertices
    and faces, no landmarks, no ground truth): the landmarks are fitted, and the transfer
    is as good as with the true landmarks and far better than no motion."""
    from types import SimpleNamespace

    from canrig_jax.autorig import ict_pose_source, transfer_poses
    from canrig_jax.autorig._data import make_head

    source = ict_pose_source(data_dir, progress=False)
    assert source.train == [] and source.test == {}
    coefficients = np.random.default_rng(123).standard_normal(100)
    truth = make_head(
        source.head,
        source.head_displacements,
        coefficients,
        "decimate_1300",
        name="bare",
        data_dir=data_dir,
    )
    bare = SimpleNamespace(vertices=truth.vertices, faces=truth.faces)
    transferred = transfer_poses(source, bare)
    assert transferred.shape == truth.displacements.shape and np.isfinite(transferred).all()
    with_landmarks = transfer_poses(source, truth)  # the head's own (true) landmarks

    def mae(p):
        return float(np.linalg.norm(p - truth.displacements, axis=-1).mean())

    no_motion = mae(np.zeros_like(transferred))
    assert mae(transferred) < 0.5 * no_motion, (mae(transferred), no_motion)
    assert mae(transferred) < 1.3 * mae(with_landmarks), (mae(transferred), mae(with_landmarks))
    # anchored transfer: what the ICT pose leaves still (below the static threshold) stays
    # exactly still, and so the error where the truth is static drops (measured 0.06 -> 0.001 mm)
    anchored = transfer_poses(source, truth, static_below=STATIC_MM / 10)
    static = np.linalg.norm(truth.displacements, axis=-1) < STATIC_MM / 10
    moved = np.linalg.norm(anchored, axis=-1) > 0
    assert 0.2 < moved.mean() < 0.8  # some of every pose is held, not all of it

    def static_mae(p):
        return float(np.linalg.norm(p - truth.displacements, axis=-1)[static].mean())

    assert static_mae(anchored) < 0.2 * static_mae(with_landmarks)
    assert mae(anchored) <= mae(with_landmarks)
    # per-part anchoring: each of the head's parts is held exactly when the ICT part it is
    # matched to is still in that pose, as a whole, and never while that part moves
    from canrig_jax.autorig._data import head_correspondence
    from canrig_jax.mesh import connected_components

    correspondence = head_correspondence(source, truth.vertices, truth.faces, truth.landmarks)
    per_part = transfer_poses(
        source, truth, correspondence, static_below=STATIC_MM / 10, anchor="part"
    )
    held = np.all(per_part == 0.0, axis=-1)  # (P, V)
    source_labels = connected_components(source.head.faces, source.head.n_vertices)
    target_labels = connected_components(truth.faces, truth.n_vertices)
    motion = np.linalg.norm(source.head_displacements, axis=-1)  # (P, Vs)
    cases = {"still": 0, "moving": 0}
    for label in np.unique(target_labels):
        members = target_labels == label
        matched = source_labels == correspondence.component_match[label]
        peak = motion[:, matched].max(axis=1)  # (P,)
        still, moving = peak < 0.5 * STATIC_MM / 10, peak > 2 * STATIC_MM / 10
        assert held[np.ix_(still, members)].all()
        assert not held[np.ix_(moving, members)].any()
        cases["still"] += int(still.sum())
        cases["moving"] += int(moving.sum())
    assert cases["still"] > 100 and cases["moving"] > 100
    # the skin moves in every pose: held nowhere per part, but per vertex partly
    skin = target_labels == np.bincount(target_labels).argmax()
    assert not held[:, skin].any() and not np.all(anchored[:, skin] == 0, axis=-1).all()
    with pytest.raises(ValueError, match="head: .*faces"):
        transfer_poses(source, SimpleNamespace(vertices=truth.vertices))


@pytest.mark.slow
def test_balanced_loss_weighs_each_pose_against_its_own_no_motion_error(small_head, tiny_poses):
    """balance_poses divides each pose's error by what predicting no motion scores on it (0.5:
    by the geometric mean of that and the training set's scale): checked against numpy, and a
    pose 100x larger does not outweigh a small one."""
    from canrig_jax.autorig._train import BALANCE_FLOOR, batch_loss, mean_square_displacement

    mesh, *_ = small_head
    n = mesh.vertices.shape[0]
    rng = np.random.default_rng(3)
    truth = np.zeros((tiny_poses.n_poses, n, 3), np.float32)
    truth[:, : n // 2] = rng.normal(0, 0.1, (tiny_poses.n_poses, n // 2, 3))
    truth[1] *= 100.0  # one pose moves 100x more than the others
    data, model = _one_head_and_small_model(mesh, truth, tiny_poses)
    reference = float(mean_square_displacement(data))
    heads, poses = jnp.array([0]), jnp.array([[0, 1, 2]])
    ops = jax.tree.map(lambda x: x[0], data.operators)
    predicted = np.asarray(model(data.poses[poses[0]], data.vertices[0], ops))
    t = np.asarray(data.displacements[0][poses[0]])
    mask = np.asarray(ops.vertex_mask, bool)
    marks = np.asarray(data.landmarks[0])

    def terms(x):  # (Q, V) -> (Q,)
        return x[:, mask].mean(axis=1) + 0.5 * x[:, marks].mean(axis=1)

    error = terms(np.sum((predicted - t) ** 2, -1))
    still = np.maximum(terms(np.sum(t**2, -1)), BALANCE_FLOOR * reference)
    drift = float(static_vertex_error(predicted, t, mask, STATIC_CM / data.scale[0]))
    for weight in (0.0, 2.0):
        balanced, _ = batch_loss(
            model, data, heads, poses, 0.5, jnp.asarray(reference), "squared", weight, True
        )
        plain, _ = batch_loss(
            model, data, heads, poses, 0.5, jnp.asarray(reference), "squared", weight, False
        )
        static = weight * drift / np.sqrt(reference)
        np.testing.assert_allclose(balanced, np.mean(error / still) + static, rtol=1e-4)
        half, _ = batch_loss(
            model, data, heads, poses, 0.5, jnp.asarray(reference), "squared", weight, 0.5
        )
        divisor = np.sqrt(reference * still)  # halfway between the plain and balanced scales
        np.testing.assert_allclose(half, np.mean(error / divisor) + static, rtol=1e-4)
    np.testing.assert_allclose(plain, np.mean(error) / reference + static, rtol=1e-4)
    # the plain loss is dominated by the large pose, the balanced one weighs poses alike
    assert error[1] / error.sum() > 0.9
    assert (error / still)[1] / (error / still).sum() < 0.9
