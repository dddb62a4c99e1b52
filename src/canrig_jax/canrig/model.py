"""CANRig (section 3.1, appendix B eq. 9a-9g) and its shape-preserving variant (section 3.2,
eq. 10), as equinox modules.

Per vertex v with canonical position s_v (on the neutral S_0) and handle h at canonical
position p_h with displacement d_h (target minus base shape at the handle):

    q_v = MLP_q(s_v)                    queries: depend only on S_0, computed once and cached
    k_h = MLP_k(p_h)                    keys
    u_h = ZP-MLP_GELU(d_h)              values, zero-preserving
    o_v = sum_h A_M[v, h] u_h           masked multi-head cross-attention (attention.py)
    S_v = S_B,v + ZP-MLP_Tanh(o_v)      output, zero-preserving

Per-head width: appendix B gives a latent size of 64 and K heads; we read the 64 as the *total*
width, split over the heads (4 heads x 16), the convention of ``torch.nn.MultiheadAttention``
(embed_dim split across num_heads), not 64 per head.

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
positional encoding, sin and cos of pi 2^k x for k = 0..L-1 per coordinate (3 + 6L inputs),
so that neighbouring vertices of different parts (upper and lower lid, upper and lower lip)
can get clearly different queries.

Options beyond the paper (all off by default; see experiments/results/canrig/
ablation_short_runs.md): ``interpolation_prior`` adds sum_h M_vh d_h / max(sum_h M_vh, 1) to
the output, so the network learns the correction to a plain mask-weighted interpolation;
``query_modulation`` multiplies the attended vector also by an affine map of the vertex's
query; ``linear_skip`` gives the zero-preserving MLPs a bias-free linear skip. All three are
linear in d or multiply the attended vector, so both exact properties still hold.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from .attention import masked_cross_attention
from .masks import CLAMP
from .mlp import ZeroPreservingMLP


def _normalisation(canonical) -> tuple[tuple[float, float, float], float]:
    canonical = np.asarray(canonical, np.float64)
    if canonical.ndim != 2 or canonical.shape[1] != 3 or len(canonical) == 0:
        raise ValueError(f"canonical: expected shape (V, 3), got {canonical.shape}")
    if not np.all(np.isfinite(canonical)):
        raise ValueError("canonical: contains non-finite values")
    centre = canonical.mean(axis=0)
    scale = float(np.sqrt(((canonical - centre) ** 2).sum(axis=1).mean())) or 1.0
    return tuple(float(c) for c in centre), scale


class CANRig(eqx.Module):
    """The CANRig network. ``encode_queries`` once per mesh, then ``__call__`` per edit."""

    query_mlp: eqx.nn.MLP
    key_mlp: eqx.nn.MLP
    value_mlp: ZeroPreservingMLP
    output_mlp: ZeroPreservingMLP
    centre: tuple[float, float, float] = eqx.field(static=True)
    position_scale: float = eqx.field(static=True)
    displacement_scale: float = eqx.field(static=True)
    n_heads: int = eqx.field(static=True)
    latent: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    n_layers: int = eqx.field(static=True)
    clamp: float = eqx.field(static=True)
    fourier: int = eqx.field(static=True)
    linear_skip: bool = eqx.field(static=True)
    query_modulation: eqx.nn.Linear | None
    interpolation_prior: bool = eqx.field(static=True)

    def __init__(
        self,
        canonical: Float[np.ndarray, "V 3"],
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
        _check_sizes(n_heads, latent, width, n_layers, displacement_scale, clamp)
        if int(fourier) < 0:
            raise ValueError(f"fourier: expected >= 0, got {fourier}")
        self.centre, self.position_scale = _normalisation(canonical)
        self.displacement_scale = float(displacement_scale)
        self.n_heads, self.latent, self.clamp = n_heads, latent, float(clamp)
        self.width, self.n_layers = int(width), int(n_layers)
        self.fourier = int(fourier)
        self.linear_skip = bool(linear_skip)
        self.interpolation_prior = bool(interpolation_prior)
        kq, kk, kv, ko, km = jax.random.split(key, 5)
        self.query_modulation = eqx.nn.Linear(latent, latent, key=km) if query_modulation else None
        mlp = dict(width_size=width, depth=n_layers - 1, activation=jax.nn.gelu)
        n_in = 3 + 6 * self.fourier
        self.query_mlp = eqx.nn.MLP(n_in, latent, **mlp, key=kq)
        self.key_mlp = eqx.nn.MLP(n_in, latent, **mlp, key=kk)
        zp = dict(width=width, n_layers=n_layers, linear_skip=self.linear_skip)
        self.value_mlp = ZeroPreservingMLP(3, latent, **zp, activation=jax.nn.gelu, key=kv)
        self.output_mlp = ZeroPreservingMLP(latent, 3, **zp, activation=jnp.tanh, key=ko)

    def normalise(self, points: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
        return (points - jnp.asarray(self.centre, points.dtype)) / self.position_scale

    def encode_position(self, points: Float[Array, "N 3"]) -> Float[Array, "N F"]:
        """Input of the query and key MLPs: the normalised position and, with ``fourier``
        octaves, its sin/cos encoding."""
        x = self.normalise(points)
        if not self.fourier:
            return x
        frequencies = jnp.pi * 2.0 ** jnp.arange(self.fourier, dtype=x.dtype)
        angles = (x[:, :, None] * frequencies).reshape(x.shape[0], -1)
        return jnp.concatenate([x, jnp.sin(angles), jnp.cos(angles)], axis=1)

    def _heads(self, x: Float[Array, "N latent"]) -> Float[Array, "heads N d"]:
        return x.reshape(x.shape[0], self.n_heads, self.latent // self.n_heads).swapaxes(0, 1)

    def encode_queries(self, canonical: Float[Array, "N 3"]) -> Float[Array, "heads N d"]:
        """Queries of vertices at their canonical (neutral) positions; cache these."""
        return self._heads(jax.vmap(self.query_mlp)(self.encode_position(canonical)))

    def encode_keys(self, handle_canonical: Float[Array, "H 3"]) -> Float[Array, "heads H d"]:
        return self._heads(jax.vmap(self.key_mlp)(self.encode_position(handle_canonical)))

    def encode_values(self, displacements, handle_base) -> Float[Array, "heads H d"]:
        del handle_base  # only the shape-preserving variant uses it
        return self._heads(jax.vmap(self.value_mlp)(displacements / self.displacement_scale))

    def vertex_modulation(self, queries: Float[Array, "N latent"] | None):
        """With ``query_modulation``: an affine map of each vertex's (cached) query, which
        multiplies the attended vector before the output MLP; else None."""
        if self.query_modulation is None or queries is None:
            return None
        return jax.vmap(self.query_modulation)(queries)

    def decode(self, attended: Float[Array, "N latent"], base, queries=None) -> Float[Array, "N 3"]:
        del base
        modulation = self.vertex_modulation(queries)
        if modulation is not None:
            attended = attended * modulation
        return jax.vmap(self.output_mlp)(attended) * self.displacement_scale

    def interpolate(
        self, mask: Float[Array, "*B N H"], displacements: Float[Array, "*B H 3"]
    ) -> Float[Array, "*B N 3"]:
        """The interpolation prior (``interpolation_prior``; else 0): each vertex moves by the
        mask-weighted mean of the handle displacements, sum_h M_h d_h / max(sum_h M_h, 1), so
        it fades out where the influences sum to less than 1. Linear in d (zero-preserving)
        and exactly 0 where every clamped mask is 0; the network learns the correction."""
        total = jnp.sum(mask, axis=-1, keepdims=True)
        return jnp.matmul(mask / jnp.maximum(total, 1.0), displacements)

    def __call__(
        self,
        queries: Float[Array, "heads N d"],
        base: Float[Array, "N 3"],
        handle_canonical: Float[Array, "H 3"],
        handle_base: Float[Array, "H 3"],
        displacements: Float[Array, "H 3"],
        mask: Float[Array, "N H"],
        beta: float | Float[Array, ""] | None = None,
    ) -> Float[Array, "N 3"]:
        """The deformed shape at the N query vertices: base + network output.

        ``mask`` is the influence (``masks.influence_mask``), clamped here at ``clamp``;
        ``beta`` (the extra attention column) is used by the shape-preserving variant only.
        """
        mask = jnp.where(mask < self.clamp, 0.0, mask)
        keys = self.encode_keys(handle_canonical)
        values = self.encode_values(displacements, handle_base)
        attended = masked_cross_attention(queries, keys, values, mask, self.attention_beta(beta))
        attended = attended.swapaxes(0, 1).reshape(queries.shape[1], -1)
        flat_queries = queries.swapaxes(0, 1).reshape(queries.shape[1], -1)
        out = base + self.decode(attended, base, flat_queries)
        if self.interpolation_prior:
            out = out + self.interpolate(mask, displacements)
        return out

    def attention_beta(self, beta):
        """The extra attention column's logit: none for plain CANRig."""
        return None


class ShapePreservingCANRig(CANRig):
    """Eq. (10): value and output inputs modulated by the base shape, an extra attention
    column ``beta`` with a zero value; vertices outside every clamped mask stay exactly at
    the base shape."""

    value_embedding: eqx.nn.Linear
    value_modulation: eqx.nn.Linear
    output_modulation: eqx.nn.Linear

    def __init__(self, canonical: Float[np.ndarray, "V 3"], *, key: PRNGKeyArray, **options):
        """The options of ``CANRig``; the value MLP takes the embedded, modulated displacement."""
        key, ke, kb, ks, kv = jax.random.split(key, 5)
        super().__init__(canonical, key=key, **options)
        width, latent = self.width, self.latent
        self.value_embedding = eqx.nn.Linear(3, width, use_bias=False, key=ke)
        self.value_modulation = eqx.nn.Linear(3, width, key=kb)
        self.output_modulation = eqx.nn.Linear(3, latent, key=ks)
        self.value_mlp = ZeroPreservingMLP(
            width,
            latent,
            width=width,
            n_layers=self.n_layers,
            activation=jax.nn.gelu,
            linear_skip=self.linear_skip,
            key=kv,
        )

    def encode_values(self, displacements, handle_base) -> Float[Array, "heads H d"]:
        embedded = jax.vmap(self.value_embedding)(displacements / self.displacement_scale)
        modulated = embedded * jax.vmap(self.value_modulation)(self.normalise(handle_base))
        return self._heads(jax.vmap(self.value_mlp)(modulated))

    def decode(self, attended: Float[Array, "N latent"], base, queries=None) -> Float[Array, "N 3"]:
        modulation = jax.vmap(self.output_modulation)(self.normalise(base))
        by_query = self.vertex_modulation(queries)
        if by_query is not None:
            modulation = modulation + by_query
        modulated = attended * modulation
        return jax.vmap(self.output_mlp)(modulated) * self.displacement_scale

    def attention_beta(self, beta):
        """The extra attention column's logit (default 0, the training value)."""
        return 0.0 if beta is None else beta


def _check_sizes(n_heads, latent, width, n_layers, displacement_scale, clamp):
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


def parameter_count(model: eqx.Module) -> int:
    """Number of trainable scalars (array leaves)."""
    leaves = jax.tree_util.tree_leaves(eqx.filter(model, eqx.is_array))
    return int(sum(leaf.size for leaf in leaves))
