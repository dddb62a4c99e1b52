"""Analytic antialiasing of silhouette edges: the gradient the hard rasteriser lacks (in the
style of nvdiffrast's antialiasing; Laine et al. 2020, section 3.4).

A hard rendering is piecewise constant in the vertices where a silhouette edge crosses the
image, so its mask has no gradient. For every pair of neighbouring pixels, horizontal and
vertical, of which exactly one is covered (``Fragments``), let f be the covered pixel's
triangle and t in [0, 1) the fraction of the way from its centre to the other centre where
the segment between them leaves f (through edge e of f, from the edge functions, which are
linear in the vertices' screen positions). Along that segment f covers [.., t]; the pixels
split at 1/2, so:

* t < 1/2: the covered pixel is uncovered over (1/2 - t): it moves that fraction towards the
  other pixel's value;
* t >= 1/2: the other pixel is covered over (t - 1/2): it moves that fraction towards the
  covered pixel's value.

Either way d(output)/dt is the difference of the two values, continuous as t crosses 1/2
(and as the edge crosses a pixel centre, where the covered pixel changes), and t carries
the gradient to the edge's two vertices. Each edge is handled by one direction of pairs:
horizontal pairs take edges steeper than 45 degrees, vertical pairs the others
(nvdiffrast's rule), so an edge is not counted twice.

Only covered / background pairs are blended (the silhouette against the background, which
is what a mask loss needs); occlusion edges inside the silhouette (a nearer surface over a
farther one) are not, unlike nvdiffrast, which finds them from the mesh's topology. The
exit edge is f's own: where the segment leaves f into an uncovered neighbour triangle
(slivers thinner than a pixel), the blend ends at f's edge, not the mesh's.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .._checks import check_finite
from ._camera import Camera, project_points
from ._hard import Fragments, check_budget, check_fragments, edge_functions, rasterise_hard
from ._raster import _check_inputs


def _pair_blend(image, uv, faces, triangle, axis: int, budget: int):
    """Blend of one direction of neighbour pairs (axis 1: horizontal, 0: vertical): the
    change of each pixel, (H W, C). The pairs with exactly one covered pixel are compacted
    first (at most ``budget`` of them): the work follows the silhouette's length."""
    height, width = triangle.shape
    covered = (triangle >= 0).ravel()
    stride = 1 if axis == 1 else width
    first_ok = np.ones((height, width), bool)
    if axis == 1:
        first_ok[:, -1] = False
    else:
        first_ok[-1] = False
    first_ok = first_ok.ravel()
    n_pixels = height * width
    shifted = jnp.concatenate([covered[stride:], jnp.zeros(stride, bool)])
    edge = first_ok & (covered != shifted)
    a = jnp.nonzero(edge, size=budget, fill_value=0)[0]
    live = jnp.arange(budget) < jnp.sum(edge)
    b = a + stride
    from_a = covered[a]  # the covered pixel of the pair is the first one
    c = jnp.where(from_a, a, b)
    o = jnp.where(from_a, b, a)
    face = jnp.maximum(triangle.ravel()[c], 0)
    corners = uv[faces[face]]  # (budget, 3, 2)
    row_c, col_c = jnp.divmod(c, width)
    row_o, col_o = jnp.divmod(o, width)
    pu_c, pv_c = col_c + 0.5, row_c + 0.5
    pu_o, pv_o = col_o + 0.5, row_o + 0.5
    *w_c, area = edge_functions(corners, pu_c, pv_c)
    *w_o, _ = edge_functions(corners, pu_o, pv_o)
    sign = jnp.sign(jnp.where(live, area, 1.0))
    e_c = jnp.stack(w_c, -1) * sign[:, None]  # >= 0: the centre is inside f
    e_o = jnp.stack(w_o, -1) * sign[:, None]
    leaves = live[:, None] & (e_o < 0)
    t_all = jnp.where(leaves, e_c / jnp.where(leaves, e_c - e_o, 1.0), jnp.inf)
    exit_edge = jnp.argmin(t_all, -1)
    t = jnp.clip(jnp.take_along_axis(t_all, exit_edge[:, None], -1)[:, 0], 0.0, 1.0)
    # the exit edge runs between the two corners other than exit_edge
    start = jnp.take_along_axis(corners, ((exit_edge + 1) % 3)[:, None, None], 1)[:, 0]
    end = jnp.take_along_axis(corners, ((exit_edge + 2) % 3)[:, None, None], 1)[:, 0]
    direction = jax.lax.stop_gradient(end - start)
    steep = jnp.abs(direction[:, 1]) >= jnp.abs(direction[:, 0])
    mine = jnp.any(leaves, -1) & (steep if axis == 1 else ~steep)
    t = jnp.where(mine, t, 0.5)
    img_c, img_o = image[c], image[o]
    to_c = jnp.where((t < 0.5)[:, None], (0.5 - t)[:, None] * (img_o - img_c), 0.0)
    to_o = jnp.where((t >= 0.5)[:, None], (t - 0.5)[:, None] * (img_c - img_o), 0.0)
    sink = jnp.where(mine, 0, n_pixels)  # pairs left over write to a slot that is dropped
    delta = jnp.zeros((n_pixels + 1, image.shape[-1]), image.dtype)
    delta = delta.at[c + sink].add(to_c).at[o + sink].add(to_o)
    return delta[:n_pixels]


def edge_pair_budget(height: int, width: int, edge_budget: float) -> int:
    """Neighbour pairs per direction that ``antialias`` blends: edge_budget x (H + W)."""
    return max(1, math.ceil(edge_budget * (height + width)))


def _antialias(image, vertices, faces, camera: Camera, fragments: Fragments, edge_budget):
    squeeze = image.ndim == 2
    if squeeze:
        image = image[..., None]
    height, width = camera.image_size
    uv, _ = project_points(camera, vertices)
    flat = image.reshape(height * width, -1)
    budget = edge_pair_budget(height, width, edge_budget)
    out = flat
    if width > 1:
        out = out + _pair_blend(flat, uv, faces, fragments.triangle, 1, budget)
    if height > 1:
        out = out + _pair_blend(flat, uv, faces, fragments.triangle, 0, budget)
    out = out.reshape(image.shape)
    return out[..., 0] if squeeze else out


_antialias_jit = eqx.filter_jit(_antialias)


def antialias(
    image: Float[ArrayLike, "H W *C"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    camera: Camera,
    fragments: Fragments,
    *,
    edge_budget: float = 8.0,
) -> Float[Array, "H W *C"]:
    """``image`` (H, W) or (H, W, C) with its silhouette edges blended by the analytic
    coverage of the covered pixels' triangles (see the module): differentiable with respect
    to ``vertices`` (through the edges' positions), the camera's arrays and ``image``.

    ``fragments``: ``rasterise_hard`` of the same ``vertices``, ``faces`` and ``camera``.
    ``image``: any per-pixel values (a mask ``fragments.covered``, a shaded image, an
    interpolated attribute), with the background's values on uncovered pixels.
    ``edge_budget`` (static): covered / background pairs blended per direction, in units of
    H + W (a silhouette's length in pixels is a small multiple of that; pairs beyond the
    budget keep their hard values). jit-, vmap- and grad-safe; concrete inputs are checked
    first (ValueError naming the argument).
    """
    vertices, faces, _ = _check_inputs(vertices, faces, camera, None)
    check_fragments(fragments, camera)
    if not isinstance(image, jax.Array | np.ndarray):
        image = np.asarray(image, np.float32)
    if image.ndim not in (2, 3) or tuple(image.shape[:2]) != tuple(camera.image_size):
        raise ValueError(
            f"image: expected shape {tuple(camera.image_size)} or "
            f"{tuple(camera.image_size)} + (C,), got {tuple(image.shape)}"
        )
    check_finite("image", image)
    check_budget("edge_budget", edge_budget)
    image = jnp.asarray(image, vertices.dtype)
    return _antialias_jit(image, vertices, faces, camera, fragments, float(edge_budget))


def silhouette(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    camera: Camera,
    fragments: Fragments | None = None,
    *,
    chunk_size: int = 4,
    chunk_budget: float = 4.0,
    edge_budget: float = 8.0,
) -> Float[Array, "H W"]:
    """Antialiased mask in [0, 1] of the mesh (1 inside, 0 on the background, blended on
    silhouette edges): hard visibility (``rasterise_hard``, or ``fragments`` when given) +
    ``antialias``; its gradient with respect to ``vertices`` moves the silhouette edges.
    ValueError naming the argument for bad input (as ``rasterise_hard`` and ``antialias``)."""
    check_budget("edge_budget", edge_budget)
    if fragments is None:
        fragments = rasterise_hard(
            vertices, faces, camera, chunk_size=chunk_size, chunk_budget=chunk_budget
        )
    vertices, faces, _ = _check_inputs(vertices, faces, camera, None)
    check_fragments(fragments, camera)
    mask = fragments.covered.astype(vertices.dtype)
    return _antialias_jit(mask, vertices, faces, camera, fragments, float(edge_budget))


__all__ = ["antialias", "silhouette"]
