"""Hard rasterisation and differentiable interpolation (deferred shading, in the style of
nvdiffrast; Laine et al. 2020, "Modular primitives for high-performance differentiable
rendering").

Two steps instead of the soft rasteriser's one:

1. ``rasterise_hard``: visibility. Which triangle is nearest at each pixel centre, and its
   depth: a z-buffer, computed without gradients (a pixel's triangle is piecewise constant
   in the vertices). Schedule: every triangle's screen box, clipped to the image, is cut into
   ``chunk_size`` x ``chunk_size`` pixel chunks; a fixed budget of chunks (static shape:
   ``chunk_budget`` x the image's chunk count + one per triangle) is handed out to the
   triangles in order (a cumulative sum and a sorted search), each chunk tests its pixels
   against its triangle (edge functions, perspective-correct depth), and two scatters
   write the z-buffer (minimum depth) and then the id of the triangle that reached it.
   The work follows the triangles' screen area, not pixels x triangles. Chunks beyond the
   budget are dropped (the last triangles in face order): ``Fragments.overflow`` counts
   them, so a caller can check nothing was lost.
2. ``interpolate``: differentiable barycentrics of each pixel centre in its visible triangle,
   recomputed from the projected vertices (gradients flow to vertex positions, the camera's
   arrays and the attributes), perspective-correct (1/z is linear in screen space), and the
   interpolated depth and per-vertex attributes.

Inside a triangle the interpolated values are smooth in the vertices; the jumps at
silhouette edges (which pixel sees which surface) carry no gradient here: ``antialias``
(``_antialias.py``) adds it. Pixel centres exactly on an edge shared by two triangles
count for both; the depth test then picks one (ties: the higher triangle index).
Triangles are not culled by orientation (like ``rasterise``); degenerate triangles (zero
screen area, e.g. the (0, 0, 0) padding of ``padded_faces``) cover nothing.
"""

import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._camera import Camera, project_points
from ._raster import _check_inputs

_AREA_EPS = 1e-9  # |twice the signed screen area| (pixels^2) below which a triangle is skipped


class Fragments(eqx.Module):
    """Visibility of a mesh through one camera (``rasterise_hard`` lists the fields)."""

    triangle: Int[Array, "H W"]
    depth: Float[Array, "H W"]
    overflow: Int[Array, ""]

    @property
    def covered(self) -> Bool[Array, "H W"]:
        """(H, W) bool: a triangle is seen at the pixel."""
        return self.triangle >= 0


class Interpolation(eqx.Module):
    """Differentiable per-pixel values of ``interpolate`` (it lists the fields)."""

    barycentric: Float[Array, "H W 3"]
    depth: Float[Array, "H W"]
    attributes: Float[Array, "H W C"] | None
    mask: Float[Array, "H W"]


def edge_functions(
    tri_uv: Float[ArrayLike, "*#batch 3 2"],
    pu: Float[ArrayLike, "*#batch"],
    pv: Float[ArrayLike, "*#batch"],
) -> tuple[
    Float[Array, "*#batch"],
    Float[Array, "*#batch"],
    Float[Array, "*#batch"],
    Float[Array, "*#batch"],
]:
    """Edge functions (twice the signed areas) of points (pu, pv) in triangles with screen
    corners ``tri_uv`` (..., 3, 2), broadcast: (w0, w1, w2, area), w_i opposite corner i,
    area = w0 + w1 + w2 (twice the triangle's signed area); w_i / area are the screen-space
    barycentric coordinates."""
    tri_uv = jnp.asarray(tri_uv)
    au, av = tri_uv[..., 0, 0], tri_uv[..., 0, 1]
    bu, bv = tri_uv[..., 1, 0], tri_uv[..., 1, 1]
    cu, cv = tri_uv[..., 2, 0], tri_uv[..., 2, 1]
    w0 = (bu - pu) * (cv - pv) - (bv - pv) * (cu - pu)
    w1 = (cu - pu) * (av - pv) - (cv - pv) * (au - pu)
    w2 = (au - pu) * (bv - pv) - (av - pv) * (bu - pu)
    return w0, w1, w2, w0 + w1 + w2


def n_chunks(n_faces: int, height: int, width: int, chunk_size: int, chunk_budget: float) -> int:
    """Static chunk count of ``rasterise_hard``: one per triangle plus ``chunk_budget`` x
    the image's area in chunks."""
    return n_faces + math.ceil(chunk_budget * height * width / chunk_size**2)


def _rasterise_hard(vertices, faces, camera: Camera, chunk_size: int, chunk_budget: float):
    vertices = jax.lax.stop_gradient(vertices)
    camera = jax.lax.stop_gradient(camera)
    height, width = camera.image_size
    uv, z = project_points(camera, vertices)
    tri_uv, tri_z = uv[faces], z[faces]  # (F, 3, 2), (F, 3)
    n_faces = faces.shape[0]
    _, _, _, area = edge_functions(tri_uv, 0.0, 0.0)
    usable = jnp.abs(area) > _AREA_EPS
    if camera.perspective:
        usable &= jnp.all(tri_z > 0, axis=1)
    # pixel index range (column, row) whose centres (index + 0.5) lie in the triangle's box
    limit = jnp.asarray([width - 1, height - 1])
    lo = jnp.clip(jnp.ceil(jnp.min(tri_uv, 1) - 0.5), 0, limit).astype(jnp.int32)
    hi = jnp.clip(jnp.floor(jnp.max(tri_uv, 1) - 0.5), -1, limit).astype(jnp.int32)
    extent = jnp.maximum(hi - lo + 1, 0)
    grid = (extent + chunk_size - 1) // chunk_size  # chunks along u and v, (F, 2)
    count = jnp.where(usable, grid[:, 0] * grid[:, 1], 0)
    ends = jnp.cumsum(count)
    total = ends[-1]
    budget = n_chunks(n_faces, height, width, chunk_size, chunk_budget)
    chunk = jnp.arange(budget)
    face = jnp.minimum(jnp.searchsorted(ends, chunk, side="right"), n_faces - 1)
    local = chunk - (ends[face] - count[face])
    across = jnp.maximum(grid[face, 0], 1)
    col0 = lo[face, 0] + (local % across) * chunk_size
    row0 = lo[face, 1] + (local // across) * chunk_size
    dr, dc = np.divmod(np.arange(chunk_size * chunk_size), chunk_size)
    cols = col0[:, None] + dc[None]  # (budget, chunk_size^2)
    rows = row0[:, None] + dr[None]
    live = (chunk < total)[:, None] & (cols <= hi[face, 0:1]) & (rows <= hi[face, 1:2])
    corners = tri_uv[face][:, None]  # (budget, 1, 3, 2)
    w0, w1, w2, area = edge_functions(corners, cols + 0.5, rows + 0.5)
    sign = jnp.sign(area)
    inside = live & (w0 * sign >= 0) & (w1 * sign >= 0) & (w2 * sign >= 0)
    fz = tri_z[face]
    safe_area = jnp.where(inside, area, 1.0)
    if camera.perspective:
        inverse = (w0 / fz[:, 0:1] + w1 / fz[:, 1:2] + w2 / fz[:, 2:3]) / safe_area
        depth = 1.0 / jnp.where(inside, inverse, 1.0)
    else:
        depth = (w0 * fz[:, 0:1] + w1 * fz[:, 1:2] + w2 * fz[:, 2:3]) / safe_area
    depth = jnp.where(inside, depth, jnp.inf).ravel()
    n_pixels = height * width
    target = jnp.where(inside, rows * width + cols, n_pixels).ravel()  # the last slot: a sink
    zbuffer = jnp.full(n_pixels + 1, jnp.inf, depth.dtype).at[target].min(depth)
    winner = inside.ravel() & (depth == zbuffer[target])
    ids = jnp.broadcast_to(face[:, None], inside.shape).ravel().astype(jnp.int32)
    triangle = jnp.full(n_pixels + 1, -1, jnp.int32).at[target].max(jnp.where(winner, ids, -1))
    triangle = triangle[:n_pixels].reshape(height, width)
    depth_image = jnp.where(triangle >= 0, zbuffer[:n_pixels].reshape(height, width), 0.0)
    overflow = jnp.maximum(total - budget, 0).astype(jnp.int32)
    return Fragments(triangle, depth_image, overflow)


_rasterise_hard_jit = eqx.filter_jit(_rasterise_hard)


def check_budget(name: str, value: Any) -> None:
    """A static work budget (chunks, edges): a finite number > 0, or a ValueError naming it."""
    if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")


def _check_chunks(chunk_size, chunk_budget) -> None:
    if not (isinstance(chunk_size, int | np.integer) and chunk_size >= 1):
        raise ValueError(f"chunk_size: expected an int >= 1, got {chunk_size!r}")
    check_budget("chunk_budget", chunk_budget)


def rasterise_hard(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    camera: Camera,
    *,
    chunk_size: int = 4,
    chunk_budget: float = 4.0,
) -> Fragments:
    """The nearest triangle and its depth at every pixel centre (a z-buffer; no gradients).

    Args:
        vertices: (V, 3) world positions; faces: (F, 3) vertex indices.
        camera: a ``Camera`` (its ``image_size`` sets H x W).
        chunk_size: pixels per side of the screen chunks a triangle's box is cut into
            (static).
        chunk_budget: chunks available, in units of the image's area (static): the budget
            is F + chunk_budget x H x W / chunk_size^2. A mesh whose triangles' screen boxes
            add up to more than chunk_budget x the image overflows (``overflow`` below).

    Returns:
        The mesh's visibility (``Fragments``) for ``interpolate``, ``silhouette`` and
        ``antialias``: ``triangle`` (H, W) int32, the index of the triangle seen at each pixel
        centre, -1 where none (background); ``depth`` (H, W), its depth along the viewing axis
        (world units), 0 on the background; ``covered`` (H, W) bool, a triangle is seen there;
        ``overflow`` () int32, the number of screen chunks beyond the budget (> 0: some
        triangles were not, or only partly, rasterised; raise ``chunk_budget``).

    jit- and vmap-safe. Concrete inputs are checked first (ValueError naming the argument:
    empty meshes, non-finite values, face indices out of range, a bad camera, vertices at or
    behind a perspective camera, bad chunk settings).
    """
    _check_chunks(chunk_size, chunk_budget)
    vertices, faces, _ = _check_inputs(vertices, faces, camera, None)
    return _rasterise_hard_jit(vertices, faces, camera, int(chunk_size), float(chunk_budget))


def _interpolate(vertices, faces, camera: Camera, fragments: Fragments, attributes):
    covered = fragments.triangle >= 0
    corners = faces[jnp.maximum(fragments.triangle, 0)]  # (H, W, 3)
    uv, z = project_points(camera, vertices)
    height, width = camera.image_size
    rows, cols = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    w0, w1, w2, area = edge_functions(uv[corners], cols, rows)
    area = jnp.where(covered & (jnp.abs(area) > _AREA_EPS), area, 1.0)
    b = jnp.stack([w0, w1, w2], -1) / area[..., None]  # screen-space barycentrics
    if camera.perspective:
        weighted = b / z[corners]
        inverse_depth = jnp.sum(weighted, -1)
        safe = jnp.where(covered, inverse_depth, 1.0)
        depth = 1.0 / safe
        b = weighted * depth[..., None]
    else:
        depth = jnp.sum(b * z[corners], -1)
    mask = covered.astype(b.dtype)
    b = b * mask[..., None]
    values = None
    if attributes is not None:
        values = jnp.einsum("hwk,hwkc->hwc", b, attributes[corners])
    return Interpolation(b, depth * mask, values, mask)


_interpolate_jit = eqx.filter_jit(_interpolate)


def check_fragments(fragments: Any, camera: Camera) -> None:
    """ValueError naming ``fragments`` unless it is a ``Fragments`` of ``camera``'s image size
    (checked on shapes; a leading view axis, under ``jax.vmap``, is the caller's)."""
    if not isinstance(fragments, Fragments):
        raise ValueError(f"fragments: expected Fragments, got {type(fragments).__name__}")
    if tuple(fragments.triangle.shape[-2:]) != tuple(camera.image_size):
        raise ValueError(
            f"fragments: image size {tuple(fragments.triangle.shape[-2:])} does not match the "
            f"camera's {tuple(camera.image_size)}"
        )


def interpolate(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    camera: Camera,
    fragments: Fragments,
    attributes: Float[ArrayLike, "V C"] | None = None,
) -> Interpolation:
    """Barycentrics, depth and ``attributes`` at every covered pixel centre, in the triangle
    ``fragments`` (from ``rasterise_hard``) sees there, recomputed from the projected
    ``vertices`` so gradients flow to ``vertices``, the camera's arrays and ``attributes``.

    ``fragments`` may come from other vertices (e.g. the neutral of a pose) as long as the
    triangles stay valid: visibility is then held fixed (first-order exact inside triangles).
    Values are 0 on the background. jit-, vmap- and grad-safe; concrete inputs are checked
    first (ValueError naming the argument).

    Returns:
        The differentiable per-pixel values (an ``Interpolation``): ``barycentric``
        (H, W, 3), the perspective-correct barycentric coordinates of the pixel centre in its
        visible triangle (they sum to 1 on covered pixels); ``depth`` (H, W), the interpolated
        depth (world units along the viewing axis); ``attributes`` (H, W, C), the
        interpolated ``attributes``, or None; ``mask`` (H, W), the hard coverage, 1.0 or 0.0
        (no gradient: ``antialias`` gives one).
    """
    vertices, faces, attributes = _check_inputs(vertices, faces, camera, attributes)
    check_fragments(fragments, camera)
    return _interpolate_jit(vertices, faces, camera, fragments, attributes)


__all__ = [
    "Fragments",
    "Interpolation",
    "check_fragments",
    "edge_functions",
    "interpolate",
    "n_chunks",
    "rasterise_hard",
]
