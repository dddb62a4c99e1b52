"""The blendshape rig with corrective terms of any order, as one differentiable function.

Racković et al. 2023, eq. (5): for weights w in R^K,

    f(w) = b0 + sum_i w_i b_i + sum_{(i,j)} w_i w_j b^{ij}
              + sum_{(i,j,k)} w_i w_j w_k b^{ijk} + sum_{(i,j,k,l)} w_i w_j w_k w_l b^{ijkl},

where the sums over combinations run only over the correctives the rig stores. A linear rig
is the same function with no corrective tables.

Correctives have local support, so each order is stored support-restricted: the union S of
vertices that any corrective of that order moves, and deltas over S only (see
``benchmarks/bench_evaluate.py`` for the measured gain over a dense layout).
"""

import functools
import operator
from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Float32, Int, Int32

from .._checks import check_finite, check_real, is_concrete, native


def _real_array(name: str, x, integer: bool = False):
    """``x`` as a JAX array of real numbers in native byte order, for a Module converter.

    Integer and boolean positions become float32 (an int32 rig would truncate the weights);
    complex numbers, strings and objects raise TypeError naming ``name``; with ``integer``
    the values must already be integers (indices are never rounded silently)."""
    if not isinstance(x, jax.Array):
        x = native(np.asarray(x))
    check_real(name, x)
    dtype = x.dtype
    if integer:
        if not (np.issubdtype(dtype, np.integer) or (x.size == 0)):
            raise TypeError(f"{name}: expected integer indices, got dtype {dtype}")
        target = jnp.int32
    elif not np.issubdtype(dtype, np.floating):
        target = jnp.float32
    else:
        target = jax.dtypes.canonicalize_dtype(dtype)
    if isinstance(x, np.ndarray):  # convert on the host: no device work before the checks
        return jnp.asarray(x.astype(target, copy=False))
    return jnp.asarray(x, target)


UNIT_IN_CM = {"mm": 0.1, "cm": 1.0, "dm": 10.0, "m": 100.0}
"""Length of one rig unit in centimetres, for ``BlendshapeRig.units``."""


_check_finite = check_finite
"""The shared check under its former private name (until every importer uses ``checks``)."""


class Corrective(eqx.Module):
    """Corrective terms of one order n (n >= 2) in a support-restricted layout.

    Attributes:
        indices: (C, n) int32 blendshape indices of each combination, distinct within a row.
        vertices: (S,) int32 strictly increasing vertices moved by any corrective of this
            order (S = V means every vertex, and ``evaluate`` then skips the scatter).
        deltas: (C, S, 3) corrective offsets on ``vertices`` (rig units).
    """

    indices: Int[Array, "C n"] = eqx.field(converter=lambda x: _real_array("indices", x, True))
    vertices: Int[Array, " S"] = eqx.field(converter=lambda x: _real_array("vertices", x, True))
    deltas: Float[Array, "C S 3"] = eqx.field(converter=lambda x: _real_array("deltas", x))

    def __check_init__(self):
        if self.indices.ndim != 2 or self.indices.shape[1] < 2:
            raise ValueError(
                f"indices: expected shape (C, n) with order n >= 2, got {self.indices.shape}"
            )
        c, s = self.indices.shape[0], self.vertices.shape[0]
        if self.vertices.ndim != 1:
            raise ValueError(f"vertices: expected shape (S,), got {self.vertices.shape}")
        if self.deltas.shape != (c, s, 3):
            raise ValueError(
                f"deltas: expected shape (C, S, 3) = ({c}, {s}, 3) to match indices and "
                f"vertices, got {self.deltas.shape}"
            )
        if is_concrete(self.indices) and c:
            rows = np.sort(np.asarray(self.indices), axis=1)
            if np.any(rows[:, 1:] == rows[:, :-1]):
                bad = np.flatnonzero(np.any(rows[:, 1:] == rows[:, :-1], axis=1))[:5]
                raise ValueError(f"indices: rows {bad.tolist()} repeat a blendshape index")
        if is_concrete(self.vertices) and s:
            if np.any(np.diff(np.asarray(self.vertices)) <= 0):
                raise ValueError("vertices: support vertices must be strictly increasing")
        check_finite("deltas", self.deltas)

    @property
    def order(self) -> int:
        return int(self.indices.shape[1])

    @classmethod
    def from_dense(
        cls,
        indices: Int[ArrayLike, "C n"] | Sequence[Sequence[int]],
        dense_deltas: Float[ArrayLike, "C V 3"],
        support_tol: float = 0.0,
    ) -> "Corrective":
        """Build from (C, V, 3) dense offsets, keeping vertices where any offset norm
        exceeds ``support_tol`` (rig units); offsets below it elsewhere are dropped."""
        dense = np.asarray(dense_deltas, dtype=np.float32)
        indices = np.asarray(indices, dtype=np.int32).reshape(dense.shape[0], -1)
        if dense.ndim != 3 or dense.shape[2] != 3:
            raise ValueError(f"dense_deltas: expected (C, V, 3), got {dense.shape}")
        magnitude = np.linalg.norm(dense, axis=2).max(axis=0, initial=0.0)
        vertices = np.flatnonzero(magnitude > support_tol).astype(np.int32)
        return cls(indices, vertices, dense[:, vertices])

    def to_dense(self, n_vertices: int) -> Float32[np.ndarray, "C V 3"]:
        """(C, V, 3) NumPy offsets on all vertices."""
        dense = np.zeros((self.indices.shape[0], n_vertices, 3), np.float32)
        dense[:, np.asarray(self.vertices)] = np.asarray(self.deltas)
        return dense


class BlendshapeRig(eqx.Module):
    """A delta blendshape rig with optional correctives of any order (Racković eq. (5)).

    Attributes:
        neutral: (V, 3) rest mesh, rig units (ICT: centimetres).
        deltas: (K, V, 3) blendshape offsets from the neutral.
        correctives: one ``Corrective`` table per order (distinct orders); ``()`` = linear.
        names: K blendshape names (static).
        faces: (F, 3) int32 triangles, or None when the rig carries no topology.
        units: length unit of ``neutral``, ``deltas`` and correctives, one of
            ``UNIT_IN_CM`` ("mm", "cm", "dm", "m"; default "cm", ICT's); metrics convert
            with it (e.g. ``inverse.metrics`` reports mm whatever the rig's unit).
    """

    neutral: Float[Array, "V 3"] = eqx.field(converter=lambda x: _real_array("neutral", x))
    deltas: Float[Array, "K V 3"] = eqx.field(converter=lambda x: _real_array("deltas", x))
    correctives: tuple[Corrective, ...] = eqx.field(converter=tuple, default=())
    names: tuple[str, ...] = eqx.field(static=True, converter=tuple, default=())
    faces: Int[Array, "F 3"] | None = eqx.field(
        converter=lambda x: None if x is None else _real_array("faces", x, True), default=None
    )
    units: str = eqx.field(static=True, default="cm")

    def __check_init__(self):
        if self.units not in UNIT_IN_CM:
            raise ValueError(f"units: expected one of {tuple(UNIT_IN_CM)}, got {self.units!r}")
        if self.neutral.ndim != 2 or self.neutral.shape[1] != 3:
            raise ValueError(f"neutral: expected shape (V, 3), got {self.neutral.shape}")
        v = self.neutral.shape[0]
        if self.deltas.ndim != 3 or self.deltas.shape[1:] != (v, 3):
            raise ValueError(
                f"deltas: expected shape (K, {v}, 3) to match neutral, got {self.deltas.shape}"
            )
        k = self.deltas.shape[0]
        if self.names and len(self.names) != k:
            raise ValueError(
                f"names: expected {k} names (one per blendshape), got {len(self.names)}"
            )
        if len(set(self.names)) != len(self.names):
            raise ValueError("names: blendshape names must be distinct")
        check_finite("neutral", self.neutral)
        check_finite("deltas", self.deltas)
        orders = [c.order for c in self.correctives]
        if len(set(orders)) != len(orders):
            raise ValueError(f"correctives: one table per order expected, got orders {orders}")
        for c in self.correctives:
            if is_concrete(c.indices) and c.indices.size:
                lo, hi = int(np.min(np.asarray(c.indices))), int(np.max(np.asarray(c.indices)))
                if lo < 0 or hi >= k:
                    raise ValueError(
                        f"correctives: order-{c.order} indices must lie in [0, {k}), "
                        f"found range [{lo}, {hi}]"
                    )
            if is_concrete(c.vertices) and c.vertices.size:
                lo, hi = int(np.min(np.asarray(c.vertices))), int(np.max(np.asarray(c.vertices)))
                if lo < 0 or hi >= v:
                    raise ValueError(
                        f"correctives: order-{c.order} support vertices must lie in [0, {v}), "
                        f"found range [{lo}, {hi}]"
                    )
        if self.faces is not None:
            if self.faces.ndim != 2 or self.faces.shape[1] != 3:
                raise ValueError(f"faces: expected shape (F, 3), got {self.faces.shape}")
            if is_concrete(self.faces) and self.faces.size:
                lo, hi = int(np.min(np.asarray(self.faces))), int(np.max(np.asarray(self.faces)))
                if lo < 0 or hi >= v:
                    raise ValueError(
                        f"faces: vertex indices must lie in [0, {v}) (the vertex count), "
                        f"found range [{lo}, {hi}]"
                    )

    @property
    def n_vertices(self) -> int:
        return int(self.neutral.shape[0])

    @property
    def n_blendshapes(self) -> int:
        return int(self.deltas.shape[0])

    def corrective(self, order: int) -> Corrective | None:
        """The table of one order, or None."""
        return next((c for c in self.correctives if c.order == order), None)

    def n_correctives(self, order: int) -> int:
        table = self.corrective(order)
        return 0 if table is None else int(table.indices.shape[0])

    def linear(self) -> "BlendshapeRig":
        """The same rig without correctives."""
        return BlendshapeRig(self.neutral, self.deltas, (), self.names, self.faces, self.units)

    def index(self, names: Sequence[str]) -> Int32[np.ndarray, " N"]:
        """Blendshape indices of ``names`` (ValueError listing unknown names)."""
        lookup = {n: i for i, n in enumerate(self.names)}
        unknown = [n for n in names if n not in lookup]
        if unknown:
            raise ValueError(f"names: unknown blendshape name(s) {unknown}")
        return np.array([lookup[n] for n in names], dtype=np.int32)


def check_weights(rig: BlendshapeRig, weights: Any) -> None:
    """Validate a weight vector against a rig (shape, and finiteness when concrete)."""
    check_real("weights", weights)
    shape = np.shape(weights)
    if shape != (rig.n_blendshapes,):
        raise ValueError(
            f"weights: expected shape ({rig.n_blendshapes},) for a rig with "
            f"{rig.n_blendshapes} blendshapes, got {shape}; batch with jax.vmap"
        )
    check_finite("weights", weights)


def combination_coefficients(
    weights: Float[Array, " K *frames"] | Float[np.ndarray, " K *frames"],
    indices: Int[Array, "C n"] | Int[np.ndarray, "C n"],
) -> Float[Array, " C *frames"] | Float[np.ndarray, " C *frames"]:
    """prod_{i in combination} w_i for every row of ``indices`` (NumPy in, NumPy out; JAX in,
    JAX out)."""
    return functools.reduce(operator.mul, [weights[indices[:, j]] for j in range(indices.shape[1])])


def evaluate(rig: BlendshapeRig, weights: Float[ArrayLike, " K"]) -> Float[Array, "V 3"]:
    """Mesh of the rig at one weight vector (eq. (5)); units follow the rig.

    jit-, vmap- and grad-safe; batch frames with ``evaluate_batch`` (or ``jax.vmap``).
    Raises ValueError (before any tracing) for a wrong shape or non-finite weights.
    """
    check_weights(rig, weights)
    if isinstance(weights, np.ndarray):
        weights = native(weights)
    weights = jnp.asarray(weights, rig.deltas.dtype)
    mesh = rig.neutral + jnp.tensordot(weights, rig.deltas, axes=1)
    for table in rig.correctives:
        if table.indices.shape[0] == 0:
            continue
        offsets = jnp.tensordot(combination_coefficients(weights, table.indices), table.deltas, 1)
        if table.vertices.shape[0] == mesh.shape[0]:  # sorted and distinct: all vertices
            mesh = mesh + offsets
        else:
            mesh = mesh.at[table.vertices].add(
                offsets, indices_are_sorted=True, unique_indices=True
            )
    return mesh


@eqx.filter_jit
def _evaluate_many(rig: BlendshapeRig, poses: Float[Array, "N K"]) -> Float[Array, "N V 3"]:
    return jax.vmap(evaluate, (None, 0))(rig, poses)


def evaluate_batch(
    rig: BlendshapeRig, poses: Float[ArrayLike, "N K"], *, chunk: int | None = None
) -> Float[Array, "N V 3"]:
    """Meshes of the rig at every row of ``poses`` (N, K): ``jax.vmap(evaluate)``, jitted.

    The compiled function is shared by every call (compiled once per rig structure and batch
    shape). With ``chunk`` the poses go through in slices of that many rows (the last one
    padded with zero poses), bounding memory at (chunk, V, 3) per step with one compiled
    shape. Traced ``poses`` (inside a caller's jit or grad) are evaluated in one slice.
    Raises ValueError/TypeError naming ``poses`` or ``chunk`` before any tracing.
    """
    if not isinstance(rig, BlendshapeRig):
        raise TypeError(f"rig: expected a BlendshapeRig, got {type(rig).__name__}")
    if chunk is not None and (
        isinstance(chunk, bool) or not isinstance(chunk, int | np.integer) or chunk < 1
    ):
        raise ValueError(f"chunk: expected a positive integer or None, got {chunk!r}")
    traced = not is_concrete(poses)
    poses = jnp.asarray(poses) if traced else native(np.asarray(poses))
    check_real("poses", poses)
    if poses.ndim != 2 or poses.shape[1] != rig.n_blendshapes:
        raise ValueError(
            f"poses: expected shape (N, {rig.n_blendshapes}) for a rig with "
            f"{rig.n_blendshapes} blendshapes, got {tuple(poses.shape)}"
        )
    if traced:
        return _evaluate_many(rig, jnp.asarray(poses))
    if not np.all(np.isfinite(poses)):
        bad = np.flatnonzero(~np.all(np.isfinite(poses), axis=1))[:5]
        raise ValueError(f"poses: non-finite weights in rows {bad.tolist()}")
    poses = jnp.asarray(poses, rig.deltas.dtype)
    n = poses.shape[0]
    if n == 0:
        return jnp.zeros((0, rig.n_vertices, 3), rig.neutral.dtype)
    if chunk is None or n <= chunk:
        return _evaluate_many(rig, poses)
    padded = jnp.concatenate([poses, jnp.zeros((-n % chunk, poses.shape[1]), poses.dtype)])
    parts = [_evaluate_many(rig, padded[i : i + chunk]) for i in range(0, n, chunk)]
    return jnp.concatenate(parts)[:n]
