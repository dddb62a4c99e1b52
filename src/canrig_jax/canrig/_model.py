"""CANRig (section 3.1, appendix B eq. 9a-9g) and its shape-preserving variant (section 3.2,
eq. 10), as equinox modules: an abstract base with the one forward pass and two final models.

Per vertex v with canonical position s_v (on the neutral S_0) and handle h at canonical
position p_h with displacement d_h (target minus base shape at the handle):

    q_v = MLP_q(s_v)                    queries: depend only on S_0, computed once and cached
    k_h = MLP_k(p_h)                    keys
    u_h = ZP-MLP_GELU(d_h)              values, zero-preserving
    o_v = sum_h A_M[v, h] u_h           masked multi-head cross-attention (_attention.py)
    S_v = S_B,v + ZP-MLP_Tanh(o_v)      output, zero-preserving

The forward pass is three steps, each over any leading batch shape: ``encode_keys`` /
``encode_values`` (handles), ``attention`` (vertices x handles), ``decode`` (vertices). A
``layout`` (``_layout.py``) may gather vertices and handles into local groups around
the attention and scatter the result back; the maths is the same function either way. Only the
values depend on the displacements: the attention weights are a function of the canonical
positions and the masks, which is what makes the Jacobian of the output with respect to the
displacements cheap (``workflows.displacement_jacobian``).

Per-head width: appendix B gives a latent size of 64 and K heads; we read the 64 as the *total*
width, split over the heads (4 heads x 16), the convention of ``torch.nn.MultiheadAttention``.

Shape-preserving variant (eq. 10): inputs are relative to the base shape S_B. The value input
is modulated by a linear map of b_h (the handle's position on S_B) and the output MLP's input
by a linear map of the vertex's base position,

    u_h = ZP-MLP_GELU((W_d d_h) * (L_b(b_h)))     o'_v = o_v * L_s(S_B,v)

(W_d bias-free, L_b and L_s affine), influences below ``clamp`` are exactly 0, and the
attention has an extra column with logit ``beta`` and a zero value. Both stay zero-preserving
in d: zero displacements give the base shape exactly, and a vertex outside every clamped mask
does not move at all.

Positions are normalised by the neutral's centre and scale, displacements by
``displacement_scale`` (rig units; ICT is in cm); these are static, never trained. With
``fourier = L > 0`` the query and key MLPs see the normalised position together with a fixed
positional encoding, sin and cos of pi 2^k x for k = 0..L-1 per coordinate (3 + 6L inputs).

Options beyond the paper (all off by default; see experiments/results/canrig/
ablation_short_runs.md): ``interpolation_prior`` adds sum_h M_vh d_h / max(sum_h M_vh, 1) to
the output, so the network learns the correction to a plain mask-weighted interpolation;
``query_modulation`` multiplies the attended vector also by an affine map of the vertex's
query; ``linear_skip`` gives the zero-preserving MLPs a bias-free linear skip; ``value_position``
(shape-preserving variant) replaces the affine L_b of the value modulation by an MLP of the
handle's encoded base position (the same encoding as the keys'), so a value can say where its
handle is, not only how it moved. All four are linear in d, multiply the attended vector or
multiply W_d d, so both exact properties still hold.
"""

import abc
import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Float64, PRNGKeyArray

from .._checkpoint import parameter_count as parameter_count  # re-exported (canrig, pbs)
from ._attention import Trace, masked_attention_weights
from ._attention_fit import gauss_newton, trace_edit
from ._handle_rig import AbstractHandleRig, FitOptions, FitState, HandleEdit
from ._layout import DENSE, Layout, Local, influence_reach
from ._masks import CLAMP
from ._mlp import ZeroPreservingMLP


@dataclasses.dataclass(frozen=True)
class Architecture:
    """Static (never trained) sizes, options and normalisation of a CANRig model."""

    centre: tuple[float, float, float]
    position_scale: float
    displacement_scale: float
    n_heads: int
    latent: int
    width: int
    n_layers: int
    clamp: float
    fourier: int
    linear_skip: bool
    interpolation_prior: bool
    value_position: bool = False


def _per_row(
    fn: Callable[..., Float[Array, " O"]], x: Float[Array, "*B F"], *more: Float[Array, "*B G"]
) -> Float[Array, "*B O"]:
    """``fn`` applied to each row (last axis) of ``x`` (and the matching rows of ``more``)."""
    lead = x.shape[:-1]
    flat = [a.reshape(-1, a.shape[-1]) for a in (x, *more)]
    out = jax.vmap(fn)(*flat)
    return out.reshape(*lead, out.shape[-1])


class AbstractCANRig(AbstractHandleRig):
    """The CANRig forward pass; ``CANRig`` and ``ShapePreservingCANRig`` are its two final
    models. ``encode_queries`` once per mesh, then ``__call__`` per edit. As a handle rig
    (``AbstractHandleRig``): ``prepare`` encodes the queries, ``deform`` is ``trace``'s shape,
    the work is laid out over the masks' reach, and ``fit`` is the whitened Gauss-Newton solve
    on the exact structured Jacobian (``_attention_fit.py``)."""

    arch: eqx.AbstractVar[Architecture]
    query_mlp: eqx.AbstractVar[eqx.nn.MLP]
    key_mlp: eqx.AbstractVar[eqx.nn.MLP]
    value_mlp: eqx.AbstractVar[ZeroPreservingMLP]
    output_mlp: eqx.AbstractVar[ZeroPreservingMLP]
    query_modulation: eqx.AbstractVar[eqx.nn.Linear | None]

    # ------------------------------------------------------------ what the variants change
    @abc.abstractmethod
    def value_input(
        self, displacements: Float[Array, "*B H 3"], handle_base: Float[Array, "*#B H 3"]
    ) -> Float[Array, "*B H F"]:
        """Input of the value MLP for each handle."""

    @abc.abstractmethod
    def output_modulation_of(
        self, base: Float[Array, "*B N 3"], queries: Float[Array, "*B N latent"]
    ) -> Float[Array, "*B N latent"] | None:
        """What multiplies the attended vector before the output MLP (None: nothing)."""

    @abc.abstractmethod
    def attention_beta(self, beta: float | Float[Array, ""] | None) -> Float[Array, ""]:
        """The extra attention column's logit, or None for no extra column."""

    # ------------------------------------------------------------ as a handle rig
    def prepare(self, canonical: Float[Array, "V 3"]) -> Float[Array, "heads V d"]:
        return self.encode_queries(canonical)

    def reach(
        self, radius: Float[np.ndarray, " H"], falloff: Float[np.ndarray, " H"]
    ) -> Float64[np.ndarray, " H"]:
        return influence_reach(radius, falloff, self.clamp)

    def local(self, prepared: Float[Array, "heads V d"], layout: Layout) -> Local:
        """The queries gathered into ``layout``'s vertex blocks (the layout's first step)."""
        return layout.vertices(prepared, axis=-2)

    def deform(
        self,
        prepared: Float[Array, "heads V d"],
        canonical: Float[Array, "V 3"],
        edit: HandleEdit,
        layout: Layout = DENSE,
        local: Local | None = None,
    ) -> Float[Array, "V 3"]:

        return trace_edit(self, prepared, canonical, edit, layout, local).shape

    def fit(
        self,
        prepared: Float[Array, "heads V d"],
        canonical: Float[Array, "V 3"],
        edit: HandleEdit,
        target: Float[Array, "V 3"],
        region: Float[Array, " V"],
        layout: Layout,
        options: FitOptions,
    ) -> FitState:

        return gauss_newton(self, prepared, canonical, edit, target, region, layout, options)

    # ------------------------------------------------------------ static attributes
    @property
    def clamp(self) -> float:
        return self.arch.clamp

    @property
    def latent(self) -> int:
        return self.arch.latent

    @property
    def n_heads(self) -> int:
        return self.arch.n_heads

    @property
    def interpolation_prior(self) -> bool:
        return self.arch.interpolation_prior

    @property
    def displacement_scale(self) -> float:
        return self.arch.displacement_scale

    # ------------------------------------------------------------ encode
    def normalise(self, points: Float[Array, "*B N 3"]) -> Float[Array, "*B N 3"]:
        centre = jnp.asarray(self.arch.centre, points.dtype)
        return (points - centre) / self.arch.position_scale

    def encode_position(self, points: Float[Array, "*B N 3"]) -> Float[Array, "*B N F"]:
        """Input of the query and key MLPs: the normalised position and, with ``fourier``
        octaves, its sin/cos encoding."""
        x = self.normalise(points)
        if not self.arch.fourier:
            return x
        frequencies = jnp.pi * 2.0 ** jnp.arange(self.arch.fourier, dtype=x.dtype)
        angles = (x[..., None] * frequencies).reshape(*x.shape[:-1], -1)
        return jnp.concatenate([x, jnp.sin(angles), jnp.cos(angles)], axis=-1)

    def split_heads(self, x: Float[Array, "*B N latent"]) -> Float[Array, "*B heads N d"]:
        x = x.reshape(*x.shape[:-1], self.n_heads, self.latent // self.n_heads)
        return jnp.moveaxis(x, -2, -3)

    def merge_heads(self, x: Float[Array, "*B heads N d"]) -> Float[Array, "*B N latent"]:
        x = jnp.moveaxis(x, -3, -2)
        return x.reshape(*x.shape[:-2], -1)

    def encode_queries(self, canonical: Float[Array, "*B N 3"]) -> Float[Array, "*B heads N d"]:
        """Queries of vertices at their canonical (neutral) positions; cache these."""
        return self.split_heads(_per_row(self.query_mlp, self.encode_position(canonical)))

    def encode_keys(self, handle_canonical: Float[Array, "*B H 3"]) -> Float[Array, "*B heads H d"]:
        return self.split_heads(_per_row(self.key_mlp, self.encode_position(handle_canonical)))

    def encode_values(
        self, displacements: Float[Array, "*B H 3"], handle_base: Float[Array, "*#B H 3"]
    ) -> Float[Array, "*B heads H d"]:
        """Values of the handles: the only step that depends on the displacements."""
        value_input = self.value_input(displacements, handle_base)
        return self.split_heads(_per_row(self.value_mlp, value_input))

    # ------------------------------------------------------------ attend
    def attention(
        self,
        queries: Float[Array, "*B heads N d"],
        keys: Float[Array, "*B heads H d"],
        mask: Float[Array, "*B N H"],
        beta: float | Float[Array, ""] | None = None,
    ) -> Float[Array, "*B heads N H"]:
        """Masked attention weights A_M (eq. 2, with the beta column of eq. 10): they depend
        on the canonical positions and the masks, never on the displacements. ``mask`` is
        clamped at ``clamp`` here."""
        mask = jnp.where(mask < self.clamp, 0.0, mask)
        scale = 1.0 / jnp.sqrt(jnp.asarray(keys.shape[-1], keys.dtype))
        logits = jnp.matmul(queries, jnp.swapaxes(keys, -1, -2)) * scale
        weights, normaliser = masked_attention_weights(
            logits, mask[..., None, :, :], self.attention_beta(beta)
        )
        return weights / normaliser

    # ------------------------------------------------------------ decode
    def decode(
        self,
        attended: Float[Array, "*B N latent"],
        base: Float[Array, "*B N 3"],
        queries: Float[Array, "*B heads N d"],
    ) -> Float[Array, "*B N 3"]:
        """The output MLP's offset of each vertex from the base shape (0 where attended = 0)."""
        modulation = self.output_modulation_of(base, self.merge_heads(queries))
        if modulation is not None:
            attended = attended * modulation
        return _per_row(self.output_mlp, attended) * self.displacement_scale

    def vertex_modulation(
        self, queries: Float[Array, "*B N latent"]
    ) -> Float[Array, "*B N latent"] | None:
        """With ``query_modulation``: an affine map of each vertex's (cached) query."""
        if self.query_modulation is None:
            return None
        return _per_row(self.query_modulation, queries)

    def interpolation_weights(self, mask: Float[Array, "*B N H"]) -> Float[Array, "*B N H"]:
        """Weights of the interpolation prior: M_vh / max(sum_h M_vh, 1), clamped masks."""
        mask = jnp.where(mask < self.clamp, 0.0, mask)
        return mask / jnp.maximum(jnp.sum(mask, axis=-1, keepdims=True), 1.0)

    def interpolate(
        self, mask: Float[Array, "*B N H"], displacements: Float[Array, "*B H 3"]
    ) -> Float[Array, "*B N 3"]:
        """The interpolation prior: each vertex moves by the mask-weighted mean of the
        handle displacements, sum_h M_h d_h / max(sum_h M_h, 1). Linear in d
        (zero-preserving) and exactly 0 where every clamped mask is 0."""
        return jnp.matmul(self.interpolation_weights(mask), displacements)

    # ------------------------------------------------------------ the one forward pass
    def trace(
        self,
        queries: Float[Array, "heads N d"],
        base: Float[Array, "N 3"],
        handle_canonical: Float[Array, "H 3"],
        handle_base: Float[Array, "H 3"],
        displacements: Float[Array, "H 3"],
        mask: Local,
        beta: float | Float[Array, ""] | None = None,
        layout: Layout = DENSE,
        local_queries: Local | None = None,
    ) -> "Trace":
        """The forward pass with its intermediates (``__call__`` returns ``.shape``).
        ``local_queries``: ``layout.vertices(queries, axis=-2)`` if cached by the caller."""
        keys = layout.handles(self.encode_keys(handle_canonical), axis=-2)
        values = layout.handles(self.encode_values(displacements, handle_base), axis=-2)
        if local_queries is None:
            local_queries = layout.vertices(queries, axis=-2)
        # local arrays, one per part of a ``PartsLayout`` (jax.tree.map over the parts)
        attention = jax.tree.map(
            lambda q, k, m: self.attention(q, k, m, beta), local_queries, keys, mask
        )
        attended = layout.scatter(
            jax.tree.map(lambda a, v: self.merge_heads(jnp.matmul(a, v)), attention, values)
        )
        shape = base + self.decode(attended, base, queries)
        if self.interpolation_prior:
            moved = jax.tree.map(self.interpolate, mask, layout.handles(displacements, axis=-2))
            shape = shape + layout.scatter(moved)
        return Trace(shape=shape, attended=attended, attention=attention)

    def __call__(
        self,
        queries: Float[Array, "heads N d"],
        base: Float[Array, "N 3"],
        handle_canonical: Float[Array, "H 3"],
        handle_base: Float[Array, "H 3"],
        displacements: Float[Array, "H 3"],
        mask: Local,
        beta: float | Float[Array, ""] | None = None,
        layout: Layout = DENSE,
        local_queries: Local | None = None,
    ) -> Float[Array, "N 3"]:
        """The deformed shape at the N vertices: base + network output (+ prior).

        ``mask`` is the influence (``masks.influence_mask``) in the layout's local form
        ((N, H) for the dense layout; see ``_layout.py``), clamped at ``clamp`` here; ``beta``
        is used by the shape-preserving variant only. ``layout`` gathers vertices and
        handles around the attention and scatters back; every layout gives the same result."""
        return self.trace(
            queries,
            base,
            handle_canonical,
            handle_base,
            displacements,
            mask,
            beta,
            layout,
            local_queries,
        ).shape


def _architecture(
    canonical: Float[ArrayLike, "V 3"],
    *,
    n_heads: int,
    latent: int,
    width: int,
    n_layers: int,
    displacement_scale: float,
    clamp: float,
    fourier: int,
    linear_skip: bool,
    interpolation_prior: bool,
) -> Architecture:
    for name, value in (("n_heads", n_heads), ("latent", latent), ("width", width)):
        if int(value) < 1:
            raise ValueError(f"{name}: expected >= 1, got {value}")
    if latent % n_heads:
        raise ValueError(f"latent: expected a multiple of n_heads={n_heads}, got {latent}")
    if n_layers < 1:
        raise ValueError(f"n_layers: expected >= 1, got {n_layers}")
    if not displacement_scale > 0:
        raise ValueError(f"displacement_scale: expected > 0, got {displacement_scale}")
    if not 0.0 <= clamp < 0.5:
        raise ValueError(f"clamp: expected in [0, 0.5), got {clamp}")
    if int(fourier) < 0:
        raise ValueError(f"fourier: expected >= 0, got {fourier}")
    canonical = np.asarray(canonical, np.float64)
    if canonical.ndim != 2 or canonical.shape[1] != 3 or len(canonical) == 0:
        raise ValueError(f"canonical: expected shape (V, 3), got {canonical.shape}")
    if not np.all(np.isfinite(canonical)):
        raise ValueError("canonical: contains non-finite values")
    centre = canonical.mean(axis=0)
    scale = float(np.sqrt(((canonical - centre) ** 2).sum(axis=1).mean())) or 1.0
    return Architecture(
        centre=(float(centre[0]), float(centre[1]), float(centre[2])),
        position_scale=scale,
        displacement_scale=float(displacement_scale),
        n_heads=int(n_heads),
        latent=int(latent),
        width=int(width),
        n_layers=int(n_layers),
        clamp=float(clamp),
        fourier=int(fourier),
        linear_skip=bool(linear_skip),
        interpolation_prior=bool(interpolation_prior),
    )


def _position_mlps(
    arch: Architecture, kq: PRNGKeyArray, kk: PRNGKeyArray
) -> tuple[eqx.nn.MLP, eqx.nn.MLP]:
    n_in = 3 + 6 * arch.fourier

    def mlp(key: PRNGKeyArray) -> eqx.nn.MLP:
        return eqx.nn.MLP(
            n_in,
            arch.latent,
            width_size=arch.width,
            depth=arch.n_layers - 1,
            activation=jax.nn.gelu,
            key=key,
        )

    return mlp(kq), mlp(kk)


def _zero_preserving(
    arch: Architecture,
    n_in: int,
    n_out: int,
    activation: Callable[[Float[Array, "*shape"]], Float[Array, "*shape"]],
    key: PRNGKeyArray,
) -> ZeroPreservingMLP:
    return ZeroPreservingMLP(
        n_in,
        n_out,
        width=arch.width,
        n_layers=arch.n_layers,
        activation=activation,
        linear_skip=arch.linear_skip,
        key=key,
    )


class CANRig(AbstractCANRig):
    """The CANRig network (section 3.1)."""

    arch: Architecture = eqx.field(static=True)
    query_mlp: eqx.nn.MLP
    key_mlp: eqx.nn.MLP
    value_mlp: ZeroPreservingMLP
    output_mlp: ZeroPreservingMLP
    query_modulation: eqx.nn.Linear | None

    def __init__(
        self,
        canonical: Float[ArrayLike, "V 3"],
        *,
        n_heads: int = 4,
        latent: int = 64,
        width: int = 64,
        n_layers: int = 3,
        displacement_scale: float = 1.0,
        clamp: float = CLAMP,
        fourier: int = 0,
        linear_skip: bool = False,
        query_modulation: bool = False,
        interpolation_prior: bool = False,
        key: PRNGKeyArray,
    ):
        self.arch = _architecture(
            canonical,
            n_heads=n_heads,
            latent=latent,
            width=width,
            n_layers=n_layers,
            displacement_scale=displacement_scale,
            clamp=clamp,
            fourier=fourier,
            linear_skip=linear_skip,
            interpolation_prior=interpolation_prior,
        )
        kq, kk, kv, ko, km = jax.random.split(key, 5)
        self.query_mlp, self.key_mlp = _position_mlps(self.arch, kq, kk)
        self.value_mlp = _zero_preserving(self.arch, 3, latent, jax.nn.gelu, kv)
        self.output_mlp = _zero_preserving(self.arch, latent, 3, jnp.tanh, ko)
        self.query_modulation = eqx.nn.Linear(latent, latent, key=km) if query_modulation else None

    def value_input(
        self, displacements: Float[Array, "*B H 3"], handle_base: Float[Array, "*#B H 3"]
    ) -> Float[Array, "*B H F"]:
        del handle_base  # only the shape-preserving variant uses it
        return displacements / self.displacement_scale

    def output_modulation_of(
        self, base: Float[Array, "*B N 3"], queries: Float[Array, "*B N latent"]
    ) -> Float[Array, "*B N latent"] | None:
        del base
        return self.vertex_modulation(queries)

    def attention_beta(self, beta: float | Float[Array, ""] | None) -> None:
        return None


class ShapePreservingCANRig(AbstractCANRig):
    """Eq. (10): value and output inputs modulated by the base shape, an extra attention
    column ``beta`` with a zero value; vertices outside every clamped mask stay exactly at
    the base shape. Takes the options of ``CANRig``."""

    arch: Architecture = eqx.field(static=True)
    query_mlp: eqx.nn.MLP
    key_mlp: eqx.nn.MLP
    value_mlp: ZeroPreservingMLP
    output_mlp: ZeroPreservingMLP
    query_modulation: eqx.nn.Linear | None
    value_embedding: eqx.nn.Linear
    value_modulation: eqx.nn.Linear | eqx.nn.MLP
    output_modulation: eqx.nn.Linear

    def __init__(
        self,
        canonical: Float[ArrayLike, "V 3"],
        *,
        key: PRNGKeyArray,
        value_position: bool = False,
        **options,
    ):
        key, ke, kb, ks, kv = jax.random.split(key, 5)
        # the plain model's parameters, drawn with the same keys as before the refactor
        plain = CANRig(canonical, key=key, **options)
        self.arch = dataclasses.replace(plain.arch, value_position=bool(value_position))
        self.query_mlp, self.key_mlp = plain.query_mlp, plain.key_mlp
        self.output_mlp, self.query_modulation = plain.output_mlp, plain.query_modulation
        width, latent = self.arch.width, self.arch.latent
        self.value_embedding = eqx.nn.Linear(3, width, use_bias=False, key=ke)
        if value_position:
            n_in = 3 + 6 * self.arch.fourier
            self.value_modulation = eqx.nn.MLP(
                n_in,
                width,
                width_size=width,
                depth=self.arch.n_layers - 1,
                activation=jax.nn.gelu,
                key=kb,
            )
        else:
            self.value_modulation = eqx.nn.Linear(3, width, key=kb)
        self.output_modulation = eqx.nn.Linear(3, latent, key=ks)
        self.value_mlp = _zero_preserving(self.arch, width, latent, jax.nn.gelu, kv)

    def value_input(
        self, displacements: Float[Array, "*B H 3"], handle_base: Float[Array, "*#B H 3"]
    ) -> Float[Array, "*B H F"]:
        embedded = _per_row(self.value_embedding, displacements / self.displacement_scale)
        if self.arch.value_position:
            position = self.encode_position(handle_base)
        else:
            position = self.normalise(handle_base)
        return embedded * _per_row(self.value_modulation, position)

    def output_modulation_of(
        self, base: Float[Array, "*B N 3"], queries: Float[Array, "*B N latent"]
    ) -> Float[Array, "*B N latent"]:
        modulation = _per_row(self.output_modulation, self.normalise(base))
        by_query = self.vertex_modulation(queries)
        return modulation if by_query is None else modulation + by_query

    def attention_beta(self, beta: float | Float[Array, ""] | None) -> Float[Array, ""]:
        """The extra attention column's logit (default 0, the training value)."""
        return jnp.asarray(0.0 if beta is None else beta)
