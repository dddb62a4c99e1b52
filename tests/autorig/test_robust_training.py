"""Training RigAnyFace beyond ICT's geometry: the smooth warps of training heads, the
mesh-quality penalties (flipped triangles, edge stretch) and the options that turn them on."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.autorig import DEFAULT_CHECKPOINT, RigAnyFaceTrainOptions
from canrig_jax.autorig._data import RiggedHead, SmoothWarp, random_warp, warp_head, warped_heads
from canrig_jax.autorig._train import flip_penalty, stretch_penalty
from canrig_jax.mesh import flipped_triangles


def grid(n: int = 6, size: float = 10.0):
    """A bumpy (n x n)-vertex sheet in the xy plane (cm), normals +z."""
    u = np.linspace(-size / 2, size / 2, n)
    x, y = np.meshgrid(u, u, indexing="ij")
    z = 0.3 * np.sin(x) * np.cos(y)
    vertices = np.stack([x, y, z], -1).reshape(-1, 3)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            faces += [(a, b, c), (a, c, d)]
    return vertices, np.asarray(faces, np.int32)


def rotation(angle_deg: float) -> np.ndarray:
    t = np.radians(angle_deg)
    return np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])


def test_penalties_vanish_on_the_truth_and_on_small_rigid_motions():
    v, f = grid()
    rng = np.random.default_rng(0)
    truth = rng.normal(0, 0.05, (3, len(v), 3))
    flip, stretch = jax.jit(flip_penalty), jax.jit(stretch_penalty)  # one compile per shape
    for penalty in (flip, stretch):
        assert float(penalty(truth, truth, v, f)) == 0.0
    # rigid turns (padded to three poses: one compiled shape), truth still: 40 degrees
    # (cos 0.77 > the margin 0.5) with a translation, 0 degrees, and 80 degrees
    moved = np.stack([(v @ rotation(a).T + t) - v for a, t in
                      ((40, [1.0, -2.0, 0.5]), (0, [0, 0, 0]), (80, [0, 0, 0]))])  # fmt: skip
    still = np.zeros_like(moved)
    assert float(flip(moved[:2].repeat([2, 1], 0), still, v, f)) == 0.0
    assert float(stretch(moved, still, v, f)) < 1e-6
    # beyond the margin a turn costs what its cosine says: 0.5 - cos(80 deg) on every
    # triangle, in one pose of three
    value = 3 * float(flip(moved, still, v, f))
    assert value == pytest.approx(0.5 - np.cos(np.radians(80)), abs=0.02)  # the sheet is bumpy


def test_flip_penalty_of_one_folded_triangle_against_a_direct_count():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float64)
    f = np.array([[0, 1, 2], [1, 3, 2]], np.int32)
    folded = np.zeros((1, 4, 3))
    folded[0, 3] = [-1.5, -1.5, 0.0]  # vertex 3 pushed through the edge 1-2: triangle 1 flips
    assert flipped_triangles(v[None] + folded, v, f)[0].tolist() == [False, True]
    # triangle 1 turns over (cosine -1), triangle 0 is untouched: (0.5 - (-1)) / 2 triangles
    assert float(flip_penalty(folded, np.zeros_like(folded), v, f, margin=0.5)) == pytest.approx(
        0.75, abs=1e-6
    )
    # the truth folding the same way costs nothing; the mask leaves the triangle out
    assert float(flip_penalty(folded, folded, v, f)) == 0.0
    assert float(flip_penalty(folded, 0 * folded, v, f, face_mask=np.array([1, 0]))) == 0.0


def test_stretch_penalty_against_direct_edge_lengths():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    f = np.array([[0, 1, 2]], np.int32)
    moved = np.zeros((1, 3, 3))
    moved[0, 1] = [1.0, 0.0, 0.0]  # vertex 1 to (2, 0, 0)
    rest = [1.0, np.sqrt(2.0), 1.0]
    now = [2.0, np.sqrt(5.0), 1.0]
    excess = [max(abs(np.log(n / r)) - 0.25, 0.0) for n, r in zip(now, rest, strict=True)]
    expected = np.mean(excess)
    got = float(stretch_penalty(moved, np.zeros_like(moved), v, f, margin=0.25))
    assert got == pytest.approx(expected, rel=1e-5)
    assert float(stretch_penalty(moved, moved, v, f)) == 0.0  # the truth stretches as much


def test_penalty_gradients_are_finite_with_padding_and_collapse():
    # padded triangles point at vertex 0 (zero area), a predicted triangle collapsed to a point
    v, f = grid(4)
    faces = np.concatenate([f, np.zeros((5, 3), np.int32)])
    mask = np.r_[np.ones(len(f)), np.zeros(5)]
    collapse = np.zeros((1, len(v), 3))
    collapse[0, f[0]] = v[f[0, 0]] - v[f[0]]  # triangle 0 collapses onto its first corner
    for penalty in (flip_penalty, stretch_penalty):
        grad = jax.jit(jax.grad(lambda d, p=penalty: p(d, jnp.zeros_like(d), v, faces, mask)))(
            jnp.asarray(collapse, jnp.float32)
        )
        assert bool(jnp.isfinite(grad).all())


def sculpted_head():
    """A closed, smooth, head-sized surface (an ellipsoid, cm) as a RiggedHead, with two
    poses and 68 'landmarks' on its front."""
    n_theta, n_phi = 12, 20
    theta = np.linspace(0.15, np.pi - 0.15, n_theta)
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([9 * np.sin(t) * np.cos(p), 12 * np.cos(t), 10 * np.sin(t) * np.sin(p)], -1)
    v = v.reshape(-1, 3)
    faces = []
    for i in range(n_theta - 1):
        for j in range(n_phi):
            a, b = i * n_phi + j, i * n_phi + (j + 1) % n_phi
            c, d = a + n_phi, b + n_phi
            faces += [(a, c, b), (b, c, d)]
    rng = np.random.default_rng(1)
    displacements = rng.normal(0, 0.1, (2, len(v), 3)).astype(np.float32)
    landmarks = np.argsort(-v[:, 2])[:68].astype(np.int32)
    return RiggedHead("sphere", v.astype(np.float32), np.asarray(faces, np.int32),
                      displacements, landmarks, np.zeros(len(v), np.int32), np.zeros(3),
                      "test")  # fmt: skip


def test_warp_is_the_identity_at_zero_amplitude_and_smooth_otherwise():
    head = sculpted_head()
    x = head.vertices.astype(np.float64)
    still = random_warp(np.random.default_rng(0), x, head.landmarks, amplitude=0, proportions=0)
    np.testing.assert_array_equal(still(x), x)
    np.testing.assert_array_equal(SmoothWarp.identity()(x), x)
    warp = random_warp(np.random.default_rng(0), x, head.landmarks)
    assert not np.allclose(warp(x), x)
    # smooth: finite-difference Jacobian near the identity at every vertex (|J - I| small)
    eps = 1e-3
    jac = np.stack([(warp(x + eps * e) - warp(x - eps * e)) / (2 * eps) for e in np.eye(3)], -1)
    assert np.linalg.norm(jac - np.eye(3), ord=2, axis=(1, 2)).max() < 0.9
    assert np.linalg.det(jac).min() > 0.3


def test_warp_head_keeps_the_topology_and_warps_the_posed_shapes():
    head = sculpted_head()
    warp = random_warp(np.random.default_rng(3), head.vertices, head.landmarks)
    out = warp_head(head, warp)
    np.testing.assert_array_equal(out.faces, head.faces)
    np.testing.assert_array_equal(out.landmarks, head.landmarks)
    x = head.vertices.astype(np.float64)
    for p in range(2):  # the posed head warped, minus the warped neutral
        expected = warp(x + head.displacements[p]) - warp(x)
        np.testing.assert_allclose(out.displacements[p], expected, atol=1e-5)
    # a linear warp (proportions only, no RBFs, no regions) scales each displacement by S
    linear = dataclasses.replace(SmoothWarp.identity(), scale=np.array([1.2, 0.9, 1.1]))
    np.testing.assert_allclose(
        warp_head(head, linear).displacements, head.displacements * [1.2, 0.9, 1.1], atol=1e-5
    )
    # a mirror turns every triangle over: refused
    mirror = dataclasses.replace(SmoothWarp.identity(), scale=np.array([-1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="warp"):
        warp_head(head, mirror)
    copies = warped_heads([head, head], 2, seed=5)
    assert [c.name for c in copies] == ["sphere/warp0", "sphere/warp1"] * 2
    assert not np.allclose(copies[0].vertices, copies[1].vertices)


@pytest.mark.parametrize(
    "field, value",
    [
        ("flip_weight", -1.0),
        ("stretch_weight", float("nan")),
        ("stretch_margin", -0.1),
        ("flip_margin", 1.5),
        ("warp_copies", -1),
        ("warp_amplitude", -1.0),
        ("warp_proportions", float("inf")),
        ("warp_radius", 0.0),
        ("warp_targets", "truth"),
    ],
)
def test_options_refuse_bad_values_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        RigAnyFaceTrainOptions(**{field: value})


def test_init_from_refuses_another_architecture():
    from canrig_jax.autorig._train import _initial_model, load_riganyface

    _, poses, _ = load_riganyface(DEFAULT_CHECKPOINT)
    with pytest.raises(ValueError, match="init_from.*width"):
        _initial_model(RigAnyFaceTrainOptions(width=32, init_from=str(DEFAULT_CHECKPOINT)), poses)
    with pytest.raises(ValueError, match="init_from: no such file"):
        _initial_model(RigAnyFaceTrainOptions(init_from="/nonexistent.eqx"), poses)
    model, scale = _initial_model(
        RigAnyFaceTrainOptions(width=64, init_from=str(DEFAULT_CHECKPOINT)), poses
    )
    assert scale == pytest.approx(model.output_scale)
