"""CANRig-PBS and the Shape Transformer on the real ICT face (60 patches, real expressions):
zero-preservation (the base shape exactly), no motion beyond every clamped mask, the per-patch
MLPs against one MLP per patch applied in a loop, the sparse entries of W_layout against the
padded gather, the Shape Transformer's independence of the handle order, resuming training
bit-identically, and bad input."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.canrig import influence_mask
from canrig_jax.mesh import edge_graph
from canrig_jax.pbs import (
    PBSTrainOptions,
    build_pbs_training_set,
    local_pbs_fit,
    patch_layout,
    pbs_basis,
    pbs_reconstruct,
    pbs_shape,
    seed_distances,
    train_pbs,
)
from canrig_jax.pbs._model import PBS_VARIANTS, ShapeTransformer, patch_means
from canrig_jax.pbs._train import predict_pbs_weights
from canrig_jax.rig import evaluate_batch, random_sparse_poses

N_PATCHES = 60


@pytest.fixture(scope="module")
def data(ict_face):
    neutral = np.asarray(ict_face.neutral, np.float32)
    faces = np.asarray(ict_face.faces)
    layout = patch_layout(neutral, faces, N_PATCHES, rings=2)
    poses = random_sparse_poses(np.random.default_rng(7), 24, ict_face.names)
    shapes = np.asarray(evaluate_batch(ict_face, poses), np.float32)
    basis, _ = pbs_basis(neutral, shapes, 6)
    distances = seed_distances(layout, edge_graph(neutral, faces))
    pool = np.random.default_rng(0).choice(len(neutral), 300, replace=False)
    return build_pbs_training_set(neutral, shapes, layout, basis, distances, pool)


def _model(data, variant, seed=0, **options):
    return PBS_VARIANTS[variant](
        np.asarray(data.neutral),
        N_PATCHES,
        data.basis.shape[0],
        width=32,
        patch_width=16,
        fourier=2,
        key=jax.random.PRNGKey(seed),
        **options,
    )


def _edit(data, n=40, seed=1):
    handles = np.random.default_rng(seed).choice(data.pool.shape[0], n, replace=False)
    return data.pool[handles], data.pool_distance[:, handles]


@pytest.mark.parametrize(
    "variant",
    [v if v == "per_patch" else pytest.param(v, marks=pytest.mark.slow) for v in PBS_VARIANTS],
)
@pytest.mark.parametrize("local_prior", [False, True])
def test_zero_displacements_give_the_base_exactly(data, variant, local_prior):
    model = _model(data, variant, local_prior=local_prior)
    h, dist = _edit(data)
    base = data.shapes[3]
    out = pbs_reconstruct(model, data, h, dist, base, base[None], 3.0, 1.0)[0]
    assert np.array_equal(np.asarray(out), np.asarray(base))
    moved = pbs_reconstruct(model, data, h, dist, base, data.shapes[5][None], 3.0, 1.0)[0]
    assert np.abs(np.asarray(moved - base)).max() > 1e-3  # and a real edit does move it


@pytest.mark.slow
@pytest.mark.parametrize("local_prior", [False, True])
def test_nothing_moves_beyond_every_clamped_mask(data, local_prior):
    model = _model(data, "per_patch", local_prior=local_prior)
    h, dist = _edit(data, n=5)
    radius, falloff = 1.0, 3.0
    base, target = data.neutral, data.shapes[2]
    weights = predict_pbs_weights(model, data, h, dist, base, target[h] - base[h], radius, falloff)
    mask = 0.5 * (1 - np.tanh(falloff * (np.asarray(dist) - radius)))  # independent numpy
    reached = (mask >= model.encoder.clamp).any(axis=1)
    assert 0 < reached.sum() < N_PATCHES
    assert np.all(np.asarray(weights)[~reached] == 0.0)
    out = np.asarray(pbs_reconstruct(model, data, h, dist, base, target[None], radius, falloff)[0])
    vertex_patches = np.asarray(data.layout.vertex_patches)
    vertex_weights = np.asarray(data.layout.vertex_weights)
    touched = ((vertex_weights > 0) & reached[vertex_patches]).any(axis=1)
    assert np.array_equal(out[~touched], np.asarray(base)[~touched])


@pytest.mark.slow
def test_an_untrained_local_prior_model_is_the_local_fit_and_its_ridge_trains(data):
    """With ``local_prior`` the output MLP's last layer starts at zero, so the untrained
    model's weights are exactly local_pbs_fit with the clamped masks and the initial ridge;
    the loss has a gradient in the ridge and in the (zero) last layer."""
    model = _model(data, "per_patch", local_prior=True, prior_ridge=0.03)
    h, dist = _edit(data)
    base, d = data.neutral, data.shapes[5][h] - data.neutral[h]
    ours = predict_pbs_weights(model, data, h, dist, base, d, 3.0, 1.0)
    mask = np.asarray(influence_mask(dist, 3.0, 1.0))
    mask = np.where(mask < model.encoder.clamp, 0.0, mask)
    fit = local_pbs_fit(np.asarray(data.basis)[:, np.asarray(h)], d, mask, 0.03)
    np.testing.assert_allclose(np.asarray(ours), np.asarray(fit), rtol=1e-4, atol=1e-5)

    def loss(model):
        return jnp.sum(predict_pbs_weights(model, data, h, dist, base, d, 3.0, 1.0) ** 2)

    grads = eqx.filter_grad(loss)(model)
    assert float(jnp.abs(grads.log_ridge)) > 0
    assert float(jnp.abs(grads.patch_mlp.layers[-1].weight).max()) > 0
    with pytest.raises(ValueError, match="handle_basis"):
        model(
            model.encode_patches(data.seeds),
            patch_means(data.layout, base),
            data.neutral[h],
            base[h],
            d,
            jnp.asarray(mask),
        )


@pytest.mark.slow
def test_per_patch_mlps_equal_one_mlp_per_patch(data):
    model = _model(data, "per_patch")
    attended = jax.random.normal(jax.random.PRNGKey(3), (N_PATCHES, model.encoder.latent))
    batched = eqx.filter_vmap(lambda mlp, x: mlp(x))(model.patch_mlp, attended)
    params, static = eqx.partition(model.patch_mlp, eqx.is_array)
    for p in (0, 17, N_PATCHES - 1):
        one = eqx.combine(jax.tree.map(lambda a, p=p: a[p], params), static)
        np.testing.assert_allclose(batched[p], one(attended[p]), rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_sparse_entries_equal_the_padded_gather(data):
    weights = jax.random.normal(jax.random.PRNGKey(4), (N_PATCHES, data.basis.shape[0]))
    padded = eqx.tree_at(lambda lay: lay.entries, data.layout, None)
    a = pbs_shape(data.layout, data.neutral, data.basis, weights)
    b = pbs_shape(padded, data.neutral, data.basis, weights)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_patch_means_are_layout_weighted_means(data):
    w = np.asarray(data.layout.vertex_weights)
    p = np.asarray(data.layout.vertex_patches)
    x = np.asarray(data.shapes[1])
    expected = np.zeros((N_PATCHES, 3))
    mass = np.zeros(N_PATCHES)
    for c in range(p.shape[1]):
        np.add.at(expected, p[:, c], w[:, c, None] * x)
        np.add.at(mass, p[:, c], w[:, c])
    np.testing.assert_allclose(
        patch_means(data.layout, jnp.asarray(x)), expected / mass[:, None], atol=1e-4
    )


@pytest.mark.slow
def test_shape_transformer_ignores_the_handle_order(data):
    model = ShapeTransformer(
        np.asarray(data.neutral),
        data.basis.shape[0],
        latent=32,
        width=32,
        key=jax.random.PRNGKey(0),
    )
    h, dist = _edit(data)
    d = data.shapes[4][h] - data.neutral[h]
    order = np.random.default_rng(2).permutation(len(h))
    a = predict_pbs_weights(model, data, h, dist, data.neutral, d, 3.0, 1.0)
    b = predict_pbs_weights(model, data, h[order], dist[:, order], data.neutral, d[order], 3.0, 1.0)
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.slow
def test_training_resumes_bit_identically(data, tmp_path):
    options = PBSTrainOptions(
        width=32,
        patch_width=16,
        fourier=2,
        steps=4,
        batch=2,
        n_handles=(20, 40),
        handle_bucket=20,
        n_vertices=64,
        checkpoint_every=2,
        log_every=1,
    )
    straight, *_ = train_pbs(data, options, progress=False)
    path = tmp_path / "ck.eqx"
    train_pbs(data, options, checkpoint=path, progress=False, stop_after=2)
    resumed, step, _, history = train_pbs(data, options, checkpoint=path, progress=False)
    assert step == 4 and len(history) == 4
    for a, b in zip(
        jax.tree.leaves(eqx.filter(straight, eqx.is_array)),
        jax.tree.leaves(eqx.filter(resumed, eqx.is_array)),
        strict=True,
    ):
        assert np.array_equal(a, b)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"model": "dense"}, "model"),
        ({"n_handles": (50, 10)}, "n_handles"),
        ({"radius_cm": (0.0, 2.0)}, "radius_cm"),
        ({"p_neutral": 1.5}, "p_neutral"),
        ({"model": "shape_transformer", "local_prior": True}, "local_prior"),
    ],
)
def test_bad_options_name_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        PBSTrainOptions(**kwargs)


@pytest.mark.slow
def test_bad_model_and_data_arguments(data):
    with pytest.raises(ValueError, match="n_patches"):
        PBS_VARIANTS["per_patch"](np.asarray(data.neutral), 0, 3, key=jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="shapes"):
        build_pbs_training_set(
            np.asarray(data.neutral),
            np.asarray(data.shapes)[:, :10],
            data.layout,
            data.basis,
            np.zeros((N_PATCHES, data.neutral.shape[0])),
            np.arange(5),
        )
    with pytest.raises(ValueError, match="pool"):
        build_pbs_training_set(
            np.asarray(data.neutral),
            np.asarray(data.shapes),
            data.layout,
            data.basis,
            np.zeros((N_PATCHES, data.neutral.shape[0])),
            np.array([-1, 3]),
        )
