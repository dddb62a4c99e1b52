"""Where the attention runs: a layout gathers vertices and handles into local groups around
the attention of ``AbstractCANRig.trace`` and scatters the result back to vertex order. It
never changes the maths, so every layout gives the dense result (up to float summation order).

``DENSE`` is the identity: every vertex attends to every handle, (N, H).

``BlockLayout`` (block-sparse inference): influence masks are local, so each vertex needs only
the handles whose clamped mask on it is non-zero. The mesh's vertices are split once into
compact blocks (``vertex_blocks``: recursive median bisection along the longest axis). Once per
handle placement, the distance from each handle to the nearest vertex of each block is kept
(``block_distance``). A clamped mask is exactly 0 beyond a distance that depends only on the
handle's radius and falloff (``influence_reach``), so per call the host lists the handles
within reach of each block (``block_layout``, at most ``width`` of them: the next power of two
above the largest count, so nothing is ever truncated and few shapes compile) without touching
the (V, H) masks. Masks and attention are then computed on (block vertices x block handles):
a handle outside a block's list has mask 0 on all of its vertices and contributes nothing.

``PartsLayout`` (``block_layout(..., parts=...)``): one width for all blocks pads every block
to the most crowded one (on the ICT face at 200 random handles / 2 cm: 14 handles reach a
block on average, 35 the most). The blocks are sorted by their count and split into a few
parts of fixed fractions, each a ``BlockLayout`` with its own width whose scatter leaves the
other parts' vertices at 0; the parts' results are summed. A layout's local form is then a
tuple with one array per part: code that works on local arrays maps over it with
``jax.tree.map`` (a single array is a one-leaf tree), so every layout runs the same code.
"""

import functools
import operator
from collections.abc import Iterable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Float32, Float64, Int, Int32, Shaped

Local = Shaped[Array, "..."] | tuple[Shaped[Array, "..."], ...]
"""An array in a layout's local form: the array itself (``DENSE``), gathered into blocks
(``BlockLayout``), or a tuple with one such array per part (``PartsLayout``)."""


class DenseLayout(eqx.Module):
    """Every vertex attends to every handle: all gathers and the scatter are identities."""

    def vertices(self, x: Shaped[Array, "*shape"], axis: int) -> Shaped[Array, "*shape"]:
        return x

    def handles(self, x: Shaped[Array, "*shape"], axis: int) -> Shaped[Array, "*shape"]:
        return x

    def distance(self, distance: Float[Array, "N H"]) -> Float[Array, "N H"]:
        return distance

    def per_handle(self, x: Float[Array, " H"]) -> Float[Array, " H"]:
        return x

    def scatter(self, x: Shaped[Array, "N F"]) -> Shaped[Array, "N F"]:
        return x

    def sum_handles(self, x: Shaped[Array, " H *C"], n_handles: int) -> Shaped[Array, " H *C"]:
        return x

    def sum_handle_pairs(
        self, x: Shaped[Array, "H H *C"], n_handles: int
    ) -> Shaped[Array, "H H *C"]:
        return x


DENSE = DenseLayout()


def _gather(x, index, axis):
    """x with ``axis`` replaced by the (G, K) ``index`` grid, the group axis G moved first."""
    axis = axis % x.ndim
    return jnp.moveaxis(jnp.take(x, index, axis=axis), axis, 0)


class BlockLayout(eqx.Module):
    """Vertex blocks and, per block, the handles within reach of it.

    Attributes:
        blocks: (B, S) vertex indices per block; padding slots hold V (a row of inf distance).
        position: (V,) each vertex's slot in the flattened (B * S) block order.
        chosen: (B, W) handle indices per block, those within reach first.
    """

    blocks: Int[Array, "*lead B S"]
    position: Int[Array, "*lead V"]
    chosen: Int[Array, "*lead B W"]

    def vertices(self, x: Shaped[Array, "..."], axis: int) -> Shaped[Array, "B ..."]:
        """``x`` with its vertex axis ``axis`` (V) replaced by the blocks' slots (S), the
        block axis (B) first: padding slots get 0."""
        pad_shape = list(x.shape)
        pad_shape[axis % x.ndim] = 1
        padded = jnp.concatenate([x, jnp.zeros(pad_shape, x.dtype)], axis=axis)
        return _gather(padded, self.blocks, axis)

    def handles(self, x: Shaped[Array, "..."], axis: int) -> Shaped[Array, "B ..."]:
        """``x`` with its handle axis ``axis`` (H) replaced by each block's chosen handles
        (W), the block axis (B) first."""
        return _gather(x, self.chosen, axis)

    def distance(self, distance: Float[Array, "V H"]) -> Float[Array, "B S W"]:
        padded = jnp.concatenate([distance, jnp.full((1, distance.shape[1]), jnp.inf)])
        return padded[self.blocks[:, :, None], self.chosen[:, None, :]]

    def per_handle(self, x: Shaped[Array, " H"]) -> Shaped[Array, "B 1 W"]:
        return x[self.chosen][:, None, :]

    def scatter(self, x: Shaped[Array, "B S F"]) -> Shaped[Array, "V F"]:
        """Back to vertex order; vertices outside these blocks (a part's ``position`` past
        its last slot) get 0."""
        flat = x.reshape(-1, x.shape[-1])
        return jnp.take(flat, self.position, axis=0, mode="fill", fill_value=0)

    def sum_handles(self, x: Shaped[Array, "B W *C"], n_handles: int) -> Shaped[Array, " H *C"]:
        """The transpose of ``handles``: per handle, the sum over the blocks listing it."""
        flat = x.reshape(-1, *x.shape[2:])
        return jax.ops.segment_sum(flat, self.chosen.reshape(-1), num_segments=n_handles)

    def sum_handle_pairs(
        self, x: Shaped[Array, "B W W *C"], n_handles: int
    ) -> Shaped[Array, "H H *C"]:
        """Per pair of handles, the sum over the blocks listing both (a normal matrix's
        assembly from per-block products)."""
        rows, cols = self.chosen[:, :, None], self.chosen[:, None, :]
        out = jnp.zeros((n_handles, n_handles, *x.shape[3:]), x.dtype)
        return out.at[rows, cols].add(x)

    @property
    def width(self) -> int:
        return int(self.chosen.shape[1])


class PartsLayout(eqx.Module):
    """Block layouts over disjoint sets of blocks, each with its own width; local forms are
    tuples (one array per part) and ``scatter``/``sum_*`` add the parts up."""

    parts: tuple[BlockLayout, ...]

    def vertices(self, x: Shaped[Array, "..."], axis: int) -> tuple[Shaped[Array, "..."], ...]:
        return tuple(part.vertices(x, axis) for part in self.parts)

    def handles(self, x: Shaped[Array, "..."], axis: int) -> tuple[Shaped[Array, "..."], ...]:
        return tuple(part.handles(x, axis) for part in self.parts)

    def distance(self, distance: Float[Array, "V H"]) -> tuple[Float[Array, "_ S _"], ...]:
        return tuple(part.distance(distance) for part in self.parts)

    def per_handle(self, x: Shaped[Array, " H"]) -> tuple[Shaped[Array, "_ 1 _"], ...]:
        return tuple(part.per_handle(x) for part in self.parts)

    def scatter(self, x: tuple[Shaped[Array, "_ S F"], ...]) -> Shaped[Array, "V F"]:
        return _sum(part.scatter(local) for part, local in zip(self.parts, x, strict=True))

    def sum_handles(
        self, x: tuple[Shaped[Array, "_ _ *C"], ...], n_handles: int
    ) -> Shaped[Array, " H *C"]:
        return _sum(
            part.sum_handles(local, n_handles) for part, local in zip(self.parts, x, strict=True)
        )

    def sum_handle_pairs(
        self, x: tuple[Shaped[Array, "_ _ _ *C"], ...], n_handles: int
    ) -> Shaped[Array, "H H *C"]:
        return _sum(
            part.sum_handle_pairs(local, n_handles)
            for part, local in zip(self.parts, x, strict=True)
        )

    @property
    def width(self) -> tuple[int, ...]:
        return tuple(part.width for part in self.parts)


Layout = DenseLayout | BlockLayout | PartsLayout


def _sum(arrays: Iterable[Array]) -> Array:
    """The sum of the parts' arrays (``sum`` would start from the int 0)."""
    return functools.reduce(operator.add, arrays)


def vertex_blocks(
    vertices: Float[ArrayLike, "V 3"], max_size: int = 48
) -> Int32[np.ndarray, "B S"]:
    """(B, S) vertex indices in compact blocks of equal size S <= max_size (-1 pads the last
    slots of blocks one shorter). Recursive median bisection along the longest extent."""
    vertices = np.asarray(vertices, np.float64)
    if max_size < 1:
        raise ValueError(f"max_size: expected >= 1, got {max_size}")
    blocks = [np.arange(len(vertices))]
    while max(len(b) for b in blocks) > max_size:
        split = []
        for block in blocks:
            points = vertices[block]
            axis = int(np.argmax(points.max(axis=0) - points.min(axis=0)))
            order = block[np.argsort(points[:, axis], kind="stable")]
            half = (len(order) + 1) // 2
            split += [order[:half], order[half:]]
        blocks = split
    size = max(len(b) for b in blocks)
    out = np.full((len(blocks), size), -1, np.int64)
    for row, block in enumerate(blocks):
        out[row, : len(block)] = block
    return out.astype(np.int32)


def block_distance(
    blocks: Int[np.ndarray, "B S"], distance: Float[ArrayLike, "V H"]
) -> Float32[np.ndarray, "B H"]:
    """(B, H) distance from each handle to the nearest vertex of each block (host, once per
    handle placement); ``distance`` is (V, H), padding slots (-1 or V) count as infinite."""
    distance = np.asarray(distance, np.float32)
    padded = np.concatenate([distance, np.full((1, distance.shape[1]), np.inf, np.float32)])
    blocks = np.where(blocks < 0, len(distance), blocks)
    return padded[blocks].min(axis=1)


def influence_reach(
    radius: float | Float[ArrayLike, "*shape"],
    falloff: float | Float[ArrayLike, "*#shape"],
    clamp: float,
) -> Float64[np.ndarray, "*shape"]:
    """(H,) distance beyond which a handle's clamped mask is exactly 0.

    0.5 (1 - tanh(g (d - r))) < clamp  <=>  d > r + atanh(1 - 2 clamp) / g. A relative and
    absolute margin of 1e-3 covers float32 rounding of the mask (a handle kept a little past
    its reach only adds zeros). With clamp 0 no mask is exactly 0 in exact arithmetic, so
    every handle reaches everywhere.
    """
    radius = np.asarray(radius, np.float64)
    if clamp <= 0.0:
        return np.full(radius.shape, np.inf)
    reach = radius + np.arctanh(1.0 - 2.0 * clamp) / np.asarray(falloff, np.float64)
    return np.asarray(reach * (1.0 + 1e-3) + 1e-3)  # an array also for scalar inputs


def block_layout(
    blocks: Int[np.ndarray | Array, "B S"],
    position: Int[np.ndarray | Array, " V"],
    nearest: Float[np.ndarray, "*lead B H"],
    reach: Float[np.ndarray, "*lead H"],
    *,
    width: int | None = None,
    multiple: int | None = None,
    parts: tuple[float, ...] | None = None,
) -> BlockLayout | PartsLayout:
    """The layout for handles whose distance to each block is ``nearest`` (``block_distance``)
    and whose masks vanish beyond ``reach`` (``influence_reach``); host-side, no device work.

    ``blocks`` and ``position`` given as device arrays (the rig's, padding already V) are
    used as they are, with no copy per call. Leading axes of ``nearest`` and ``reach`` give a
    batch of layouts (one per edit, for ``jax.vmap``) sharing one ``width``: the next power
    of two above the largest count of handles within reach of a block (at most H), the
    next multiple of ``multiple`` if given (tighter, more shapes to compile: the fit's
    Jacobian costs grow with the width), or ``width`` if given (it must be enough).

    ``parts`` (fractions summing to 1, e.g. (0.6, 0.3, 0.1)): a ``PartsLayout`` instead, the
    blocks sorted by their count of handles within reach (the most over a batch) and split
    at these fractions, each part with its own width (a fixed number of blocks per part, so
    only the widths vary between calls)."""
    nearest = np.asarray(nearest, np.float32)
    within = nearest <= np.asarray(reach)[..., None, :]  # (..., B, H)
    if multiple is not None and not multiple >= 1:
        raise ValueError(f"multiple: expected an integer >= 1, got {multiple}")
    if parts is not None:
        if width is not None:
            raise ValueError("width: not with parts (each part takes its own width)")
        return _parts_layout(blocks, position, within, parts, multiple)
    return _layout_within(blocks, position, within, width, multiple)


def _layout_within(blocks, position, within, width, multiple) -> BlockLayout:
    """``block_layout`` from the (..., B, H) table of which handles reach which block."""
    h = within.shape[-1]
    most = max(int(within.sum(axis=-1).max(initial=0)), 1)
    if multiple is None:
        needed = min(1 << (most - 1).bit_length(), h)
    else:
        needed = min(-(-most // multiple) * multiple, h)
    if width is None:
        width = needed
    elif not needed <= width <= h:
        raise ValueError(f"width: expected {needed} <= width <= {h}, got {width}")
    # handles within reach first (stable: by index), then the nearest others (mask 0 there)
    order = np.argsort(~within, axis=-1, kind="stable")[..., :width]
    lead = order.shape[:-2]
    if lead or not isinstance(blocks, jax.Array) or not isinstance(position, jax.Array):
        blocks = np.where(np.asarray(blocks) < 0, len(position), blocks).astype(np.int32)
        blocks = jnp.asarray(np.broadcast_to(blocks, (*lead, *blocks.shape)))
        position = jnp.asarray(np.broadcast_to(position, (*lead, *np.shape(position))))
    chosen = jnp.asarray(order.astype(np.int32))
    return BlockLayout(blocks=blocks, position=position, chosen=chosen)


def _parts_layout(blocks, position, within, fractions, multiple) -> PartsLayout:
    fractions = np.asarray(fractions, np.float64)
    if fractions.ndim != 1 or not len(fractions) or not np.all(fractions > 0):
        raise ValueError(f"parts: expected positive fractions, got {fractions.tolist()}")
    if not np.isclose(fractions.sum(), 1.0):
        raise ValueError(f"parts: the fractions must sum to 1, got {fractions.sum():g}")
    blocks = np.where(np.asarray(blocks) < 0, len(position), np.asarray(blocks)).astype(np.int32)
    n_blocks, n_vertices = blocks.shape[0], len(position)
    counts = within.sum(axis=-1).reshape(-1, n_blocks).max(axis=0)  # most over the batch
    order = np.argsort(counts, kind="stable")
    ends = np.round(np.cumsum(fractions) * n_blocks).astype(int)
    ends[-1] = n_blocks
    layouts = []
    for start, end in zip(np.r_[0, ends[:-1]], ends, strict=True):
        if end <= start:
            continue
        ids = order[start:end]
        part_blocks = blocks[ids]
        flat = part_blocks.ravel()
        # the other parts' vertices point past the last slot: their scatter is 0
        part_position = np.full(n_vertices, flat.size, np.int32)
        valid = flat < n_vertices
        part_position[flat[valid]] = np.flatnonzero(valid)
        layouts.append(
            _layout_within(part_blocks, part_position, within[..., ids, :], None, multiple)
        )
    return PartsLayout(parts=tuple(layouts))
