"""A differentiable soft rasteriser in JAX (SoftRas-style; Liu et al. 2019).

For every pixel p and triangle f (projected by a ``Camera``):

* d(p, f): screen distance from the pixel centre to the triangle (pixels; 0 inside),
  D_f = 2 sigmoid(-d / sigma): the triangle's soft coverage of the pixel, 1 inside, decaying
  outside. SoftRas's D = sigmoid(signed distance / sigma) is 1/2 on every edge, so a pixel on
  the edge shared by two triangles of one surface reads 3/4 and the surface behind shows
  through the seams; the one-sided D keeps a closed surface opaque;
* silhouette(p) = 1 - prod_f (1 - D_f) (a soft mask; exactly the coverage as sigma -> 0);
* each triangle's depth at p: perspective-correct interpolation (1/z linear in screen space)
  with the barycentric coordinates clipped to the triangle, z_f;
* blending weights w_f = softmax_f((log D_f + c_f) / gamma), c_f = (far - z_f) / (far - near)
  the triangle's closeness in [0, 1] (near/far: the mesh's depth range): the
  nearest covering triangle dominates. Coverage and closeness share the temperature gamma
  (SoftRas divides only the closeness by it): a nearer triangle then takes over a pixel only
  where its coverage D exceeds exp(-closeness gain), within about sigma of its edge, instead of
  bleeding sigma / gamma pixels over the covering triangles behind it;
* depth(p) = sum_f w_f z_f, and any per-vertex attribute a (V, C) is
  attribute(p) = sum_f w_f sum_i b'_fi a_{f_i}, with perspective-correct barycentrics b'. The
  weights sum to one, so a constant attribute interpolates to that constant everywhere.

As sigma, gamma -> 0 (``RasterSettings.hard()``) this is the hard rasteriser: the
silhouette is the triangles' coverage and depth / attributes are the nearest covering
triangle's (a z-buffer). Triangles are not culled by orientation (the depth blend hides the
back of the head, as SoftRas does).

One computation, two schedules: ``_fragments`` evaluates a set of pixels against a set of
triangles. The default tiled path splits the image into ``tile_size`` squares and gives each
tile the ``faces_per_tile`` nearest triangles whose screen box, grown by ``cutoff * sigma``
pixels, touches it (a triangle further away covers the tile with D < sigmoid(-cutoff)); the
dense path (``tile_size=None``) evaluates every triangle at every pixel in chunks. A tile
with more candidates than ``faces_per_tile`` drops the farthest:
``Rendering.max_faces_in_tile`` reports the largest candidate count, so a caller can check
nothing was dropped.
"""

import dataclasses
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._checks import check_finite, is_concrete
from ._camera import Camera, check_camera, project_points, screen_displacement

_NEG = -1e30
_FLOAT = jnp.result_type(float)  # float32, or float64 under jax_enable_x64
_LOG_ZERO = -40.0  # log(1 - D) where D = 1


@dataclasses.dataclass(frozen=True)
class RasterSettings:
    """Softness and schedule of the rasteriser (static: a change recompiles).

    Attributes:
        sigma: edge softness in pixels (D = sigmoid(signed distance / sigma)), > 0.
        gamma: blend temperature (closeness is a fraction of the mesh's depth range), > 0.
        tile_size: tile edge in pixels, or None for the dense schedule.
        faces_per_tile: candidate triangles kept per tile.
        cutoff: a triangle farther than ``cutoff * sigma`` pixels from a tile is skipped.
        pixel_chunk: pixels per chunk of the dense schedule.
    """

    sigma: float = 0.5
    gamma: float = 1e-2
    tile_size: int | None = 8
    faces_per_tile: int = 128
    cutoff: float = 8.0
    pixel_chunk: int = 2048

    def __post_init__(self):
        for name in ("sigma", "gamma", "cutoff"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
        if self.tile_size is not None and not (
            isinstance(self.tile_size, int) and self.tile_size >= 1
        ):
            raise ValueError(f"tile_size: expected an int >= 1 or None, got {self.tile_size!r}")
        for name in ("faces_per_tile", "pixel_chunk"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name}: expected an int >= 1, got {value!r}")

    @classmethod
    def hard(cls, **changes) -> "RasterSettings":
        """The hard limit: sigma = 1e-5 pixels, gamma = 1e-6 (a z-buffer, numerically)."""
        return cls(**{"sigma": 1e-5, "gamma": 1e-6, **changes})


class Rendering(eqx.Module):
    """Per-pixel outputs of ``rasterise`` (H = height, W = width).

    Attributes:
        silhouette: (H, W) soft coverage in [0, 1].
        depth: (H, W) blended depth (world units along the viewing axis); where the
            silhouette is ~0 it is the depth of the nearest triangles, not a background.
        attributes: (H, W, C) interpolated per-vertex attributes, or None.
        max_faces_in_tile: () largest number of candidate triangles of a tile (tiled
            schedule; > ``faces_per_tile`` means some far triangles were dropped), or the
            number of triangles (dense schedule).
    """

    silhouette: Float[Array, "H W"]
    depth: Float[Array, "H W"]
    attributes: Float[Array, "H W C"] | None
    max_faces_in_tile: Int[Array, ""]


def _segment_distance2(pu, pv, su, sv, eu, ev):
    """Squared distance of pixels (1, P) to segments s-e (K, 1), component arrays, and the
    parameter t in [0, 1] of the closest point s + t (e - s)."""
    du, dv = eu - su, ev - sv
    t = ((pu - su) * du + (pv - sv) * dv) / jnp.maximum(du * du + dv * dv, 1e-12)
    t = jnp.clip(t, 0.0, 1.0)
    return (pu - su - t * du) ** 2 + (pv - sv - t * dv) ** 2, t


def _fragments(pixels, tri_uv, tri_depth, tri_attr, valid, near, far, sigma, gamma, perspective):
    """Soft rasterisation of pixels (P, 2) against triangles (K, 3, 2) / (K, 3) / (K, 3, C)
    with ``valid`` (K,): (silhouette (P,), depth (P,), attributes (P, C)).

    Written on (K, P) arrays of scalars, triangles on the leading axis (no trailing axes of
    2 or 3, and the backward pass's sums over pixels run along the contiguous axis: XLA on
    CPU is several times slower otherwise)."""
    pu, pv = pixels[None, :, 0], pixels[None, :, 1]  # (1, P)
    au, bu, cu = tri_uv[:, 0, 0:1], tri_uv[:, 1, 0:1], tri_uv[:, 2, 0:1]  # (K, 1)
    av, bv, cv = tri_uv[:, 0, 1:2], tri_uv[:, 1, 1:2], tri_uv[:, 2, 1:2]
    area = (bu - au) * (cv - av) - (bv - av) * (cu - au)  # (K, 1) signed, twice the area
    ok = valid[:, None] & (jnp.abs(area) > 1e-8)
    inv_area = 1.0 / jnp.where(ok, area, 1.0)
    # barycentric coordinates: edge functions, linear in the pixel
    b0 = ((bu - pu) * (cv - pv) - (bv - pv) * (cu - pu)) * inv_area  # (K, P)
    b1 = ((cu - pu) * (av - pv) - (cv - pv) * (au - pu)) * inv_area
    b2 = 1.0 - b0 - b1
    inside = (b0 >= 0.0) & (b1 >= 0.0) & (b2 >= 0.0)
    d_ab, t_ab = _segment_distance2(pu, pv, au, av, bu, bv)
    d_bc, t_bc = _segment_distance2(pu, pv, bu, bv, cu, cv)
    d_ca, t_ca = _segment_distance2(pu, pv, cu, cv, au, av)
    ab_first = d_ab <= jnp.minimum(d_bc, d_ca)
    bc_first = ~ab_first & (d_bc <= d_ca)
    dist2 = jnp.where(ab_first, d_ab, jnp.where(bc_first, d_bc, d_ca))
    dist = jnp.sqrt(dist2 + 1e-12)
    # one-sided coverage: D = 1 inside, 2 sigmoid(-d / sigma) at distance d outside
    x = -jnp.where(inside, 0.0, dist) / sigma  # <= 0
    xs = jnp.minimum(x, -1e-6)
    tail = jnp.log1p(jnp.exp(xs))
    log_covered = jnp.where(inside, 0.0, jnp.log(2.0) + xs - tail)
    log_uncovered = jnp.where(inside | ~ok, _LOG_ZERO, jnp.log(-jnp.expm1(xs)) - tail)
    silhouette = -jnp.expm1(jnp.sum(jnp.where(ok, log_uncovered, 0.0), axis=0))
    # outside: barycentrics of the triangle's closest point (on the closest edge), which stay
    # continuous as a triangle turns edge-on (clipping the barycentrics would not)
    zero = jnp.zeros_like(t_ab)
    e0 = jnp.where(ab_first, 1.0 - t_ab, jnp.where(bc_first, zero, t_ca))
    e1 = jnp.where(ab_first, t_ab, jnp.where(bc_first, 1.0 - t_bc, zero))
    c0 = jnp.where(inside, b0, e0)
    c1 = jnp.where(inside, b1, e1)
    c2 = 1.0 - c0 - c1
    total = 1.0
    z0, z1, z2 = tri_depth[:, 0:1], tri_depth[:, 1:2], tri_depth[:, 2:3]
    if perspective:  # 1/z is linear in screen space
        w0, w1, w2 = c0 / z0, c1 / z1, c2 / z2
        depth = total / (w0 + w1 + w2)
        scale = depth / total
    else:
        w0, w1, w2 = c0, c1, c2
        depth = (c0 * z0 + c1 * z1 + c2 * z2) / total
        scale = 1.0 / total
    closeness = (far - depth) / jnp.maximum(far - near, 1e-12)
    logits = jnp.where(ok, (log_covered + closeness) / gamma, _NEG)
    weights = jax.nn.softmax(logits, axis=0)  # (K, P)
    pixel_depth = jnp.sum(weights * depth, 0)
    attributes = None
    if tri_attr is not None:
        ws = weights * scale
        attributes = (
            (ws * w0).T @ tri_attr[:, 0]
            + (ws * w1).T @ tri_attr[:, 1]
            + (ws * w2).T @ tri_attr[:, 2]
        )
    return silhouette, pixel_depth, attributes


def _pixel_centres(height: int, width: int):
    rows, cols = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    return jnp.stack([cols + 0.5, rows + 0.5], -1).astype(jnp.float32)  # (H, W, 2) as (u, v)


def _rasterise(vertices, faces, camera: Camera, attributes, settings: RasterSettings):
    height, width = camera.image_size
    uv, z = project_points(camera, vertices)
    tri_uv, tri_depth = uv[faces], z[faces]
    tri_attr = None if attributes is None else attributes[faces]
    n_faces = faces.shape[0]
    valid = jnp.all(tri_depth > 0, axis=1) if camera.perspective else jnp.ones(n_faces, bool)
    near, far = jnp.min(z), jnp.max(z)
    kwargs = dict(
        near=near,
        far=far,
        sigma=settings.sigma,
        gamma=settings.gamma,
        perspective=camera.perspective,
    )
    centres = _pixel_centres(height, width)
    if settings.tile_size is None:
        n_pixels = height * width
        chunk = min(settings.pixel_chunk, n_pixels)
        n_chunks = -(-n_pixels // chunk)
        flat = jnp.pad(centres.reshape(-1, 2), ((0, n_chunks * chunk - n_pixels), (0, 0)))

        def one(pixels):
            return _fragments(pixels, tri_uv, tri_depth, tri_attr, valid, **kwargs)

        sil, dep, att = jax.lax.map(one, flat.reshape(n_chunks, chunk, 2))

        def image(x: Array) -> Array:
            flat = x.reshape(n_chunks * chunk, *x.shape[2:])[:n_pixels]
            return flat.reshape(height, width, *x.shape[2:])

        attributes = None if att is None else image(att)
        return Rendering(image(sil), image(dep), attributes, jnp.asarray(n_faces, jnp.int32))
    t = settings.tile_size
    k = min(settings.faces_per_tile, n_faces)
    ny, nx = -(-height // t), -(-width // t)
    margin = settings.cutoff * settings.sigma
    tri_uv_s = jax.lax.stop_gradient(tri_uv)
    lo = jnp.min(tri_uv_s, axis=1) - margin  # (F, 2)
    hi = jnp.max(tri_uv_s, axis=1) + margin
    tile_lo = jnp.stack(
        jnp.meshgrid(jnp.arange(nx) * t, jnp.arange(ny) * t, indexing="xy"), -1
    ).reshape(-1, 2)  # (T, 2) as (u, v), row-major over tiles
    tile_hi = tile_lo + t
    overlap = (
        valid[None]
        & jnp.all(lo[None] <= tile_hi[:, None], -1)
        & jnp.all(hi[None] >= tile_lo[:, None], -1)
    )  # (T, F)
    face_closeness = (far - jnp.min(jax.lax.stop_gradient(tri_depth), 1)) / jnp.maximum(
        far - near, 1e-12
    )
    # priority: triangles facing the camera (the visible surface of a closed, outward-oriented
    # mesh; screen v points down, so they have negative signed area), then the nearest
    edge1, edge2 = tri_uv_s[:, 1] - tri_uv_s[:, 0], tri_uv_s[:, 2] - tri_uv_s[:, 0]
    facing = (edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0]) < 0
    score = jnp.where(overlap, 1.0 + 2.0 * facing[None] + face_closeness[None], 0.0)
    top, index = jax.lax.top_k(score, k)
    chosen = top > 0
    max_count = jnp.max(jnp.sum(overlap, 1)).astype(jnp.int32)
    tile_pixels = jnp.pad(centres, ((0, ny * t - height), (0, nx * t - width), (0, 0)))
    tile_pixels = (
        tile_pixels.reshape(ny, t, nx, t, 2).transpose(0, 2, 1, 3, 4).reshape(-1, t * t, 2)
    )

    def one_tile(pixels, idx, ok):
        attr = None if tri_attr is None else tri_attr[idx]
        return _fragments(pixels, tri_uv[idx], tri_depth[idx], attr, ok, **kwargs)

    sil, dep, att = jax.vmap(one_tile)(tile_pixels, index, chosen)

    def image(x: Array) -> Array:
        rest = x.shape[2:]
        x = x.reshape(ny, nx, t, t, *rest).swapaxes(1, 2).reshape(ny * t, nx * t, *rest)
        return x[:height, :width]

    attributes = None if att is None else image(att)
    return Rendering(image(sil), image(dep), attributes, max_count)


_rasterise_jit = eqx.filter_jit(_rasterise)


def _check_inputs(vertices, faces, camera, attributes) -> tuple[Array, Array, Array | None]:
    """Plain-Python checks at the public boundary (concrete values only)."""
    check_camera(camera)
    if not hasattr(vertices, "shape"):
        vertices = np.asarray(vertices, np.float32)
    if vertices.ndim != 2 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), got {tuple(vertices.shape)}")
    if vertices.shape[0] < 3:
        raise ValueError(f"vertices: an empty mesh ({vertices.shape[0]} vertices)")
    check_finite("vertices", vertices)
    if not hasattr(faces, "shape"):
        faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F, 3), got {tuple(faces.shape)}")
    if faces.shape[0] == 0:
        raise ValueError("faces: an empty mesh (no triangles)")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces: expected integer vertex indices, got dtype {faces.dtype}")
    if is_concrete(faces):
        f = np.asarray(faces)
        if f.min() < 0 or f.max() >= vertices.shape[0]:
            raise ValueError(
                f"faces: indices must lie in [0, {vertices.shape[0]}), got [{f.min()}, {f.max()}]"
            )
    if attributes is not None:
        if not hasattr(attributes, "shape"):
            attributes = np.asarray(attributes, np.float32)
        if attributes.ndim != 2 or attributes.shape[0] != vertices.shape[0]:
            raise ValueError(
                f"attributes: expected shape ({vertices.shape[0]}, C), "
                f"got {tuple(attributes.shape)}"
            )
        check_finite("attributes", attributes)
    if camera.perspective and is_concrete(vertices) and is_concrete(camera.rotation):
        depth = np.asarray(project_points(camera, jnp.asarray(vertices, jnp.float32))[1])
        behind = int(np.sum(depth <= 1e-6 * max(1.0, float(np.abs(depth).max()))))
        if behind:
            raise ValueError(
                f"camera: {behind} of {vertices.shape[0]} vertices are at or behind the camera "
                "(is the camera inside the mesh, or facing away from it?)"
            )
    return (
        jnp.asarray(vertices, _FLOAT),
        jnp.asarray(faces, jnp.int32),
        None if attributes is None else jnp.asarray(attributes, _FLOAT),
    )


def rasterise(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    camera: Camera,
    attributes: Float[ArrayLike, "V C"] | None = None,
    *,
    settings: RasterSettings = RasterSettings(),  # noqa: B008 (frozen, hashable)
) -> Rendering:
    """Soft silhouette, depth and interpolated ``attributes`` of a triangle mesh.

    jit-, vmap- and grad-safe (batch views or poses with ``jax.vmap``; gradients flow to
    ``vertices``, ``attributes`` and the camera's arrays). Concrete inputs are checked first
    (ValueError naming the argument: empty meshes, non-finite values, face indices out of
    range, a bad camera, vertices at or behind a perspective camera).
    """
    if not isinstance(settings, RasterSettings):
        raise ValueError(f"settings: expected RasterSettings, got {type(settings).__name__}")
    vertices, faces, attributes = _check_inputs(vertices, faces, camera, attributes)
    return _rasterise_jit(vertices, faces, camera, attributes, settings)


def vertex_normals(
    vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> Float[Array, "V 3"]:
    """Area-weighted unit vertex normals, differentiable (``canrig_jax.mesh.vertex_normals``
    is the NumPy one)."""
    vertices, faces = jnp.asarray(vertices), jnp.asarray(faces)
    v0, v1, v2 = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    cross = jnp.cross(v1 - v0, v2 - v0)
    normals = jnp.zeros_like(vertices)
    for j in range(3):
        normals = normals.at[faces[:, j]].add(cross)
    length2 = jnp.sum(normals**2, -1, keepdims=True)
    safe = length2 > 1e-24
    return jnp.where(safe, normals / jnp.sqrt(jnp.where(safe, length2, 1.0)), 0.0)


DEFAULT_LIGHTS = ((0.4, 0.5, 0.77), (-0.6, 0.1, 0.4))
"""Directions towards two fixed lights (world; normalised on use): a key light front,
up and right, and a weaker fill from the left."""


def lambert_image(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    camera: Camera,
    *,
    lights: Float[ArrayLike, "L 3"] | Sequence[Sequence[float]] = DEFAULT_LIGHTS,
    intensities: Float[ArrayLike, " L"] | Sequence[float] = (0.8, 0.35),
    ambient: float = 0.15,
    background: float = 0.0,
    settings: RasterSettings = RasterSettings(),  # noqa: B008
) -> tuple[Float[Array, "H W"], Rendering]:
    """Lambert-shaded grey image of the mesh under fixed directional lights:
    ambient + sum_l intensity_l max(0, n . l) with the interpolated vertex normal n,
    composited over ``background`` with the soft silhouette. Returns (image, rendering)."""
    lights = np.asarray(lights, np.float64)
    intensities = np.asarray(intensities, np.float64)
    if lights.ndim != 2 or lights.shape[1] != 3 or not np.all(np.isfinite(lights)):
        raise ValueError(f"lights: expected finite (L, 3) directions, got shape {lights.shape}")
    if np.any(np.linalg.norm(lights, axis=1) < 1e-12):
        raise ValueError("lights: a light direction has zero length")
    if intensities.shape != (lights.shape[0],):
        raise ValueError(f"intensities: expected {lights.shape[0]} values")
    vertices, faces, _ = _check_inputs(vertices, faces, camera, None)
    directions = jnp.asarray(lights / np.linalg.norm(lights, axis=1, keepdims=True), jnp.float32)
    normals = vertex_normals(vertices, faces)
    rendering = _rasterise_jit(vertices, faces, camera, normals, settings)
    n = rendering.attributes
    assert n is not None  # rasterised with the normals as attributes
    n = n / jnp.sqrt(jnp.sum(n**2, -1, keepdims=True) + 1e-12)
    diffuse = jnp.maximum(jnp.einsum("hwc,lc->hwl", n, directions), 0.0)
    shade = ambient + diffuse @ jnp.asarray(intensities, jnp.float32)
    alpha = rendering.silhouette
    return alpha * shade + (1.0 - alpha) * background, rendering


def displacement_field(
    neutral: Float[ArrayLike, "V 3"],
    posed: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    camera: Camera,
    *,
    settings: RasterSettings = RasterSettings(),  # noqa: B008
) -> Rendering:
    """The 2D displacement field of a pose: each vertex's screen displacement neutral ->
    ``posed`` (pixels, ``screen_displacement``) interpolated over the neutral's pixels
    (``attributes`` (H, W, 2): where each visible neutral surface point moves on screen)."""
    _check_inputs(posed, faces, camera, None)
    neutral, faces, _ = _check_inputs(neutral, faces, camera, None)
    flow = screen_displacement(camera, neutral, jnp.asarray(posed, jnp.float32))
    return _rasterise_jit(neutral, faces, camera, flow, settings)
