"""The fast path on the real ICT head: hard visibility (``rasterise_hard``) against NumPy ray
casting, differentiable interpolation against the soft rasteriser's hard limit, gradients of
interpolation and of the antialiased silhouette against finite differences, bad input."""

from __future__ import annotations

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.render import (
    RasterSettings,
    antialias,
    interpolate,
    look_at,
    orbit_cameras,
    rasterise,
    rasterise_hard,
    ray_cast,
    silhouette,
)
from canrig_jax.render._hard import Fragments

from .test_raster import front_camera


@pytest.mark.parametrize(
    "projection", ["perspective", pytest.param("orthographic", marks=pytest.mark.slow)]
)
def test_visibility_matches_ray_casting(head, projection):
    """Coverage and nearest depth of every pixel centre against Moeller-Trumbore ray casting
    (float64): the z-buffer is exact up to pixel centres on edges."""
    vertices, faces = head
    kwargs = {"ortho_width": 40.0} if projection == "orthographic" else {"fov_degrees": 30.0}
    camera = front_camera(vertices, 64, projection=projection, **kwargs)
    fragments = rasterise_hard(vertices, faces, camera)
    assert int(fragments.overflow) == 0
    hit, depth = ray_cast(vertices, faces, camera)
    mask = np.asarray(fragments.covered)
    assert mask.mean() > 0.2
    iou = (mask & hit).sum() / (mask | hit).sum()
    assert iou > 0.998, iou
    both = mask & hit
    error = np.abs(np.asarray(fragments.depth)[both] - depth[both])
    assert np.median(error) < 1e-4  # cm
    assert np.mean(error < 0.01) > 0.995  # all but pixels exactly on occluding edges
    assert np.all(np.asarray(fragments.depth)[~mask] == 0.0)


def test_interpolation_matches_the_soft_hard_limit(head):
    """On interior pixels (inside their triangle by a margin), the fast path's
    depth and interpolated attributes equal the soft rasteriser's in its hard limit; the
    perspective-correct barycentrics sum to 1 and reproduce the world position's depth."""
    vertices, faces = head
    camera = front_camera(vertices, 32, fov_degrees=30.0)
    attributes = np.concatenate(
        [vertices, np.random.default_rng(1).standard_normal((len(vertices), 2))], 1
    ).astype(np.float32)
    fragments = rasterise_hard(vertices, faces, camera)
    fast = interpolate(vertices, faces, camera, fragments, attributes)
    soft = rasterise(
        vertices,
        faces,
        camera,
        attributes,
        settings=RasterSettings.hard(tile_size=4, faces_per_tile=faces.shape[0]),
    )
    # interior: the pixel centre is inside its triangle by a margin (there the soft
    # rasteriser's hard limit is that triangle's value)
    d_fast, d_soft = np.asarray(fast.depth), np.asarray(soft.depth)
    covered = np.asarray(fragments.covered)
    interior = covered & (np.asarray(fast.barycentric).min(-1) > 1e-3)
    assert interior.sum() > 150
    assert np.max(np.abs(d_fast - d_soft)[interior]) < 1e-3  # cm, at ~60 cm
    a_fast, a_soft = np.asarray(fast.attributes), np.asarray(soft.attributes)
    assert np.max(np.abs(a_fast - a_soft)[interior]) < 2e-3
    b = np.asarray(fast.barycentric)
    assert np.allclose(b.sum(-1)[covered], 1.0, atol=1e-5)
    assert np.all(b[~covered] == 0.0) and np.all(np.asarray(fast.mask) == covered)
    # the interpolated world position lies at the interpolated depth
    local = (a_fast[..., :3] - np.asarray(camera.position)) @ np.asarray(camera.rotation).T
    assert np.max(np.abs(-local[..., 2] - d_fast)[covered]) < 1e-3


@pytest.mark.slow
def test_antialiased_area_follows_the_silhouette(head):
    """Scaling the head by (1 + s) about the viewing axis (orthographic) scales its screen
    area by (1 + s)^2: the antialiased mask's sum (~ the covered area) must have the
    derivative 2 x area at s = 0. The hard mask's derivative is 0: the gradient is all the
    antialiasing's, and it must have about the right size and the right sign."""
    vertices, faces = head
    camera = front_camera(vertices, 96, projection="orthographic", ortho_width=50.0)
    axis = np.asarray(camera.position) - 60.0 * -np.asarray(camera.rotation[2])
    v0 = jnp.asarray(vertices)
    offset = v0 - jnp.asarray(axis, jnp.float32)
    # scale only across the viewing axis (x, y in the camera frame)
    across = jnp.asarray(np.asarray(camera.rotation[:2]).T @ np.asarray(camera.rotation[:2]))

    def area(s):
        v = v0 + s * offset @ across
        return jnp.sum(silhouette(v, faces, camera))

    value, slope = jax.value_and_grad(area)(0.0)
    covered = float(jnp.sum(rasterise_hard(v0, faces, camera).covered))
    # measured at 96^2: the antialiased area 1-4 % and its slope 6 % short of the covered
    # pixels' (11 % at 64^2, where more triangles are pixel-sized: the
    # blend ends at the covered pixel's own triangle's edge, also where a sliver triangle
    # next to it continues the surface: see _antialias.py); a missing or doubled edge
    # direction would be 30-50 % off
    assert abs(float(value) - covered) < 0.07 * covered
    assert abs(float(slope) - 2.0 * covered) < 0.1 * 2.0 * covered, (float(slope), covered)


GRADIENT_CHECK = """
import jax, sys
jax.config.update("jax_enable_x64", True)
import numpy as np, jax.numpy as jnp
from canrig_jax.render import interpolate, look_at, rasterise_hard, silhouette
data = np.load(sys.argv[1])
v0, faces = jnp.asarray(data["v"], jnp.float64), jnp.asarray(data["f"])
size = 40
camera = look_at(np.asarray(v0.mean(0)) + [0, 0, 60.0], np.asarray(v0.mean(0)), image_size=size)
rng = np.random.default_rng(0)
w = jnp.asarray(rng.standard_normal((3, size, size)))
attribute = jnp.asarray(rng.standard_normal((v0.shape[0], 1)))
assert v0.dtype == jnp.float64
worst = []
for term in range(3):
    def loss(v):
        fragments = rasterise_hard(v, faces, camera)  # recomputed: visibility moves too
        if term == 0:
            return jnp.sum(w[0] * silhouette(v, faces, camera, fragments))
        values = interpolate(v, faces, camera, fragments, attribute)
        return (jnp.sum(w[1] * values.attributes[..., 0]), jnp.sum(w[2] * values.depth))[term - 1]
    loss = jax.jit(loss)
    g = jax.grad(loss)(v0)
    assert bool(jnp.all(jnp.isfinite(g))) and float(jnp.linalg.norm(g)) > 0
    error = 0.0
    for seed in range(3):
        u = g if seed == 0 else jnp.asarray(rng.standard_normal(v0.shape)) * (jnp.abs(g) > 0)
        u = u / jnp.linalg.norm(u)
        fd = (loss(v0 + 1e-6 * u) - loss(v0 - 1e-6 * u)) / 2e-6
        error = max(error, float(jnp.abs(fd - jnp.sum(g * u)) / jnp.abs(fd)))
    worst.append(error)
print(*worst)
"""


@pytest.mark.slow
def test_gradients_match_finite_differences(head):
    """float32: directional derivatives of the antialiased silhouette and of an interpolated
    attribute + depth against central differences (5e-3 cm ~ 5e-3 px), visibility
    recomputed at each evaluation (the float64 test is tighter)."""
    vertices, faces = head
    camera = front_camera(vertices, 32)
    rng = np.random.default_rng(0)
    w = jnp.asarray(rng.standard_normal((2, 32, 32)), jnp.float32)
    attribute = jnp.asarray(rng.standard_normal((len(vertices), 1)), jnp.float32)
    v0 = jnp.asarray(vertices)

    @jax.jit
    def losses(v):
        fragments = rasterise_hard(v, faces, camera)
        values = interpolate(v, faces, camera, fragments, attribute)
        mask = silhouette(v, faces, camera, fragments)
        return jnp.stack(
            [
                jnp.sum(w[0] * mask),
                jnp.sum(w[1] * values.attributes[..., 0]) + 0.1 * jnp.sum(w[1] * values.depth),
            ]
        )

    jacobian = jax.jacrev(losses)(v0)  # (2, V, 3)
    for term in range(2):
        g = jacobian[term]
        assert float(jnp.linalg.norm(g)) > 0
        u = jnp.asarray(rng.standard_normal(v0.shape), jnp.float32) * (jnp.abs(g) > 0)
        u = u / jnp.linalg.norm(u)
        fd = (losses(v0 + 5e-3 * u)[term] - losses(v0 - 5e-3 * u)[term]) / 1e-2
        error = float(jnp.abs(fd - jnp.sum(g * u)) / jnp.abs(fd))
        assert error < 2e-2, (term, error)


@pytest.mark.slow
def test_gradients_match_finite_differences_float64(head, tmp_path):
    """Directional derivatives (along the gradient and two random directions over the
    vertices that matter) of the antialiased silhouette, an interpolated attribute and the
    interpolated depth against central differences, float64, 1e-6 cm steps, visibility
    recomputed at every evaluation (a subprocess: x64 is process-wide)."""
    path = tmp_path / "head.npz"
    np.savez(path, v=head[0], f=head[1])
    out = subprocess.run(
        [sys.executable, "-c", GRADIENT_CHECK, str(path)], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-2000:]
    errors = [float(x) for x in out.stdout.split()[-3:]]
    assert max(errors) < 1e-6, errors


def test_overflow_is_reported(head):
    """A chunk budget too small for the mesh reports its overflow; the default one does not."""
    vertices, faces = head
    camera = front_camera(vertices, 64)
    small = rasterise_hard(vertices, faces, camera, chunk_size=1, chunk_budget=0.05)
    assert int(small.overflow) > 0
    assert int(rasterise_hard(vertices, faces, camera).overflow) == 0


@pytest.mark.slow
def test_vmap_over_views_matches_a_loop(head):
    """``jax.vmap`` over views gives each view's fragments and antialiased masks."""
    vertices, faces = head
    cameras = orbit_cameras(vertices.mean(0), 60.0, [-30.0, 20.0], image_size=32)
    v = jnp.asarray(vertices)

    def both(c):
        fragments = rasterise_hard(v, faces, c)
        return fragments.triangle, silhouette(v, faces, c, fragments)

    tri, masks = jax.jit(jax.vmap(both))(cameras)
    for i in range(2):
        c = jax.tree.map(lambda x, i=i: x[i], cameras)
        t1, m1 = both(c)
        assert np.array_equal(np.asarray(tri[i]), np.asarray(t1))
        assert np.allclose(np.asarray(masks[i]), np.asarray(m1), atol=1e-6)
    assert not np.array_equal(np.asarray(tri[0]), np.asarray(tri[1]))


@pytest.mark.bad_input
def test_bad_input(head):
    vertices, faces = head
    camera = front_camera(vertices, 16)
    fragments = rasterise_hard(vertices, faces, camera)
    with pytest.raises(ValueError, match="chunk_size"):
        rasterise_hard(vertices, faces, camera, chunk_size=0)
    with pytest.raises(ValueError, match="chunk_budget"):
        rasterise_hard(vertices, faces, camera, chunk_budget=-1.0)
    with pytest.raises(ValueError, match="vertices"):
        rasterise_hard(np.full_like(vertices, np.nan), faces, camera)
    with pytest.raises(ValueError, match="faces"):
        rasterise_hard(vertices, faces[:0], camera)
    with pytest.raises(ValueError, match="camera"):
        rasterise_hard(vertices, faces, look_at(vertices.mean(0), [0, 0, -100.0], image_size=16))
    with pytest.raises(ValueError, match="fragments"):
        interpolate(vertices, faces, front_camera(vertices, 20), fragments)
    with pytest.raises(ValueError, match="fragments"):
        silhouette(vertices, faces, camera, fragments.triangle)
    with pytest.raises(ValueError, match="attributes"):
        interpolate(vertices, faces, camera, fragments, np.zeros((3, 1)))
    with pytest.raises(ValueError, match="image"):
        antialias(np.zeros((16, 15)), vertices, faces, camera, fragments)
    with pytest.raises(ValueError, match="edge_budget"):
        antialias(np.zeros((16, 16)), vertices, faces, camera, fragments, edge_budget=0)
    assert isinstance(fragments, Fragments)
