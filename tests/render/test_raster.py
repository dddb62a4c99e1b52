"""The differentiable rasteriser on the real ICT head: gradients against finite differences,
the hard limit against trimesh ray casting, schedules, invariants, batching, bad input."""

from __future__ import annotations

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.render import (
    Camera,
    RasterSettings,
    displacement_field,
    lambert_image,
    look_at,
    orbit_cameras,
    project_points,
    rasterise,
    ray_cast,
    screen_displacement,
)
from canrig_jax.render._camera import camera_depth


def front_camera(vertices, size, **kwargs):
    centre = vertices.mean(0)
    return look_at(centre + np.array([0.0, 0.0, 60.0]), centre, image_size=size, **kwargs)


@pytest.mark.parametrize(
    "projection", ["perspective", pytest.param("orthographic", marks=pytest.mark.slow)]
)
def test_hard_limit_matches_ray_casting(head, projection):
    vertices, faces = head
    kwargs = {"ortho_width": 40.0} if projection == "orthographic" else {"fov_degrees": 30.0}
    camera = front_camera(vertices, 40, projection=projection, **kwargs)
    settings = RasterSettings.hard(tile_size=4, faces_per_tile=faces.shape[0])
    r = rasterise(vertices, faces, camera, settings=settings)
    hit, depth = ray_cast(vertices, faces, camera)
    mask = np.asarray(r.silhouette) > 0.5
    iou = (mask & hit).sum() / (mask | hit).sum()
    assert iou > 0.995, iou
    both = mask & hit
    error = np.abs(np.asarray(r.depth)[both] - depth[both])
    assert np.median(error) < 1e-3  # cm
    assert np.mean(error < 0.01) > 0.99  # all but pixels exactly on occluding edges


@pytest.mark.slow
def test_orthographic_hard_depth_is_the_plane_distance(head):
    """Orthographic: a pixel's hard depth equals the depth of the surface point whose
    interpolated world position it reports, and the mask matches the perspective one's shape
    at a long focal distance."""
    vertices, faces = head
    camera = front_camera(vertices, 48, projection="orthographic", ortho_width=40.0)
    r = rasterise(vertices, faces, camera, vertices, settings=RasterSettings.hard())
    mask = np.asarray(r.silhouette) > 0.5
    assert mask.mean() > 0.2
    point_depth = np.asarray(camera_depth(camera, r.attributes))
    assert np.max(np.abs(point_depth - np.asarray(r.depth))[mask]) < 1e-3


GRADIENT_CHECK = """
import jax, sys
jax.config.update("jax_enable_x64", True)
import numpy as np, jax.numpy as jnp
from canrig_jax.render import RasterSettings, look_at, rasterise
data = np.load(sys.argv[1])
v0, faces = jnp.asarray(data["v"], jnp.float64), jnp.asarray(data["f"])
camera = look_at(np.asarray(v0.mean(0)) + [0, 0, 60.0], np.asarray(v0.mean(0)), image_size=32)
settings = RasterSettings(sigma=1.0, gamma=0.5, tile_size=4, faces_per_tile=faces.shape[0])
rng = np.random.default_rng(0)
w = jnp.asarray(rng.standard_normal((3, 32, 32)))
attribute = jnp.asarray(rng.standard_normal((v0.shape[0], 1)))
worst = 0.0
for term in range(3):
    def loss(v):
        r = rasterise(v, faces, camera, attribute, settings=settings)
        return (jnp.sum(w[0] * r.silhouette), jnp.sum(w[1] * r.silhouette * r.attributes[..., 0]),
                jnp.sum(w[2] * r.silhouette * r.depth))[term]
    loss = jax.jit(loss)
    g = jax.grad(loss)(v0)
    for seed in range(2):
        u = g if seed == 0 else jnp.asarray(rng.standard_normal(v0.shape)) * (jnp.abs(g) > 0)
        u = u / jnp.linalg.norm(u)
        fd = (loss(v0 + 1e-5 * u) - loss(v0 - 1e-5 * u)) / 2e-5
        worst = max(worst, float(jnp.abs(fd - jnp.sum(g * u)) / jnp.abs(fd)))
print(worst)
"""


@pytest.mark.slow
def test_gradient_matches_finite_differences(head):
    """Directional derivatives of a loss on the silhouette and depth against central
    differences in float32 (step 2e-3 cm ~ 2e-3 px here), dense schedule (the tiled one
    equals it: ``test_tiles_equal_the_dense_schedule``)."""
    vertices, faces = head
    camera = front_camera(vertices, 32, fov_degrees=30.0)
    settings = RasterSettings(sigma=1.0, gamma=0.5, tile_size=None)
    weights = jnp.asarray(np.random.default_rng(0).standard_normal((2, 32, 32)), jnp.float32)

    @jax.jit
    def loss(v):
        r = rasterise(v, faces, camera, settings=settings)
        return jnp.sum(weights[0] * r.silhouette) + 0.1 * jnp.sum(
            weights[1] * r.silhouette * r.depth
        )

    v0 = jnp.asarray(vertices)
    grad = jax.grad(loss)(v0)
    assert bool(jnp.all(jnp.isfinite(grad)))
    direction = grad / jnp.linalg.norm(grad)  # random directions: the float64 test
    eps = 2e-3
    fd = (loss(v0 + eps * direction) - loss(v0 - eps * direction)) / (2 * eps)
    error = float(jnp.abs(fd - jnp.sum(grad * direction)) / jnp.abs(fd))
    assert error < 0.02, error


@pytest.mark.slow
def test_gradient_matches_finite_differences_float64(head, tmp_path):
    """All three outputs (silhouette, an interpolated attribute, depth) in float64 with
    1e-5 cm steps: attribute interpolation on sliver triangles is too curved for float32
    steps, so its check needs float64 (a subprocess: x64 is process-wide)."""
    path = tmp_path / "head.npz"
    np.savez(path, v=head[0], f=head[1])
    out = subprocess.run(
        [sys.executable, "-c", GRADIENT_CHECK, str(path)], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert float(out.stdout.split()[-1]) < 1e-5


@pytest.mark.slow
def test_tiles_equal_the_dense_schedule(head):
    vertices, faces = head
    camera = front_camera(vertices, 40)
    attribute = vertices - vertices.mean(0)
    dense = rasterise(vertices, faces, camera, attribute, settings=RasterSettings(tile_size=None))
    tiled = rasterise(
        vertices, faces, camera, attribute, settings=RasterSettings(faces_per_tile=faces.shape[0])
    )
    # tiles skip triangles farther than cutoff * sigma (each would add < 2 sigmoid(-8))
    np.testing.assert_allclose(tiled.silhouette, dense.silhouette, atol=5e-3)
    # depth and attributes where the head is (outside they follow the candidate set)
    mask = np.asarray(dense.silhouette) > 0.5
    np.testing.assert_allclose(
        np.asarray(tiled.depth)[mask], np.asarray(dense.depth)[mask], atol=1e-3
    )
    np.testing.assert_allclose(
        np.asarray(tiled.attributes)[mask], np.asarray(dense.attributes)[mask], atol=1e-3
    )
    assert int(dense.max_faces_in_tile) == faces.shape[0]


@pytest.mark.slow
def test_interpolation_invariants(head):
    vertices, faces = head
    camera = front_camera(vertices, 48)
    constant = np.tile(np.array([[2.5, -1.0]], np.float32), (vertices.shape[0], 1))
    r = rasterise(vertices, faces, camera, constant)
    np.testing.assert_allclose(r.attributes, np.broadcast_to([2.5, -1.0], (48, 48, 2)), atol=1e-4)
    silhouette = np.asarray(r.silhouette)
    assert silhouette.min() >= 0.0 and silhouette.max() <= 1.0
    assert silhouette[24, 24] == pytest.approx(1.0)  # the face is opaque: no seams
    assert silhouette[0, 0] < 1e-3  # a corner is empty
    # perspective-correct interpolation: the interpolated world position lies at the
    # rendered depth (hard limit)
    hard = rasterise(vertices, faces, camera, vertices, settings=RasterSettings.hard())
    mask = np.asarray(hard.silhouette) > 0.5
    point_depth = np.asarray(camera_depth(camera, hard.attributes))
    assert np.max(np.abs(point_depth - np.asarray(hard.depth))[mask]) < 1e-3
    # the interpolated point projects back into its own pixel
    uv, _ = project_points(camera, hard.attributes)
    rows, cols = np.nonzero(mask)
    np.testing.assert_allclose(np.asarray(uv)[rows, cols, 0], cols + 0.5, atol=2e-2)
    np.testing.assert_allclose(np.asarray(uv)[rows, cols, 1], rows + 0.5, atol=2e-2)


@pytest.mark.slow
def test_displacement_field_of_a_translation(head):
    """An orthographic camera sees a translation in its image plane as one constant flow of
    focal * t pixels; a pose equal to the neutral has zero flow."""
    vertices, faces = head
    camera = front_camera(vertices, 32, projection="orthographic", ortho_width=40.0)
    shift = np.array([0.5, -0.25, 0.3], np.float32)
    field = displacement_field(vertices, vertices + shift, faces, camera)
    expected = float(camera.focal) * np.array([0.5, 0.25])  # v points down
    np.testing.assert_allclose(field.attributes, np.broadcast_to(expected, (32, 32, 2)), atol=1e-4)
    assert float(jnp.abs(screen_displacement(camera, vertices, vertices)).max()) == 0.0


@pytest.mark.slow
def test_vmap_over_views_and_poses(head):
    vertices, faces = head
    cameras = orbit_cameras(vertices.mean(0), 60.0, [-30.0, 0.0, 30.0], image_size=24)
    poses = jnp.stack([vertices, vertices * 1.01, vertices + 0.3])

    def render(v, camera):
        return rasterise(v, faces, camera).silhouette

    batched = jax.jit(jax.vmap(jax.vmap(render, (None, 0)), (0, None)))(poses, cameras)
    assert batched.shape == (3, 3, 24, 24)
    for p in range(3):
        for c in range(3):
            camera = jax.tree.map(lambda x, c=c: x[c], cameras)
            np.testing.assert_allclose(batched[p, c], render(poses[p], camera), atol=1e-5)
    assert not np.allclose(batched[0, 0], batched[0, 2])  # the views differ


@pytest.mark.slow
def test_lambert_image_is_lit_from_the_light(head):
    vertices, faces = head
    camera = front_camera(vertices, 32)
    front, r = lambert_image(vertices, faces, camera, lights=[(0, 0, 1)], intensities=[1.0])
    back, _ = lambert_image(vertices, faces, camera, lights=[(0, 0, -1)], intensities=[1.0])
    mask = np.asarray(r.silhouette) > 0.99
    assert np.asarray(front)[mask].mean() > 0.8
    lit = np.abs(np.asarray(back)[mask] - 0.15) > 0.02  # ambient only, but for the few
    assert lit.mean() < 0.02  # pixels where an inner surface faces backwards (ear, lips)
    assert np.asarray(front)[0, 0] < 1e-3  # background


@pytest.mark.bad_input
def test_bad_input(head):
    vertices, faces = head
    camera = front_camera(vertices, 16)
    with pytest.raises(ValueError, match="focal"):
        rasterise(
            vertices,
            faces,
            Camera(camera.rotation, camera.position, jnp.asarray(0.0), camera.principal, (16, 16)),
        )
    inside = look_at(vertices.mean(0), vertices.mean(0) + [0, 0, 1.0], image_size=16)
    with pytest.raises(ValueError, match="camera: .* behind the camera"):
        rasterise(vertices, faces, inside)
    with pytest.raises(ValueError, match="faces: an empty mesh"):
        rasterise(vertices, np.zeros((0, 3), np.int32), camera)
    with pytest.raises(ValueError, match="vertices: an empty mesh"):
        rasterise(np.zeros((0, 3), np.float32), faces, camera)
    bad = vertices.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="vertices: contains non-finite"):
        rasterise(bad, faces, camera)
    with pytest.raises(ValueError, match="faces: indices"):
        rasterise(vertices, faces + vertices.shape[0], camera)
    with pytest.raises(ValueError, match="attributes"):
        rasterise(vertices, faces, camera, np.ones((3, 2), np.float32))
    for size in (0, (16, 0), -3):
        with pytest.raises(ValueError, match="image_size"):
            look_at([0, 0, 10.0], [0, 0, 0], image_size=size)
    with pytest.raises(ValueError, match="fov_degrees"):
        look_at([0, 0, 10.0], [0, 0, 0], image_size=8, fov_degrees=0.0)
    with pytest.raises(ValueError, match="ortho_width"):
        look_at([0, 0, 10.0], [0, 0, 0], image_size=8, projection="orthographic", ortho_width=0)
    with pytest.raises(ValueError, match="sigma"):
        RasterSettings(sigma=0.0)
