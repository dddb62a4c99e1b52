"""CANRig-PBS (section 4, eqs. 6-8) and the Shape Transformer baseline ([CZG*22]): networks
that predict patch-blendshape weights S_pred (P x (B - 1)) from handle displacements, so that a
whole 26,719-vertex head is S = S_base + W_layout S_pred S_basis (``_pbs.py``).

**CANRig-PBS** reuses the CANRig encoder (``ShapePreservingCANRig``: keys from the handles'
canonical positions, zero-preserving values from their displacements modulated by the base
shape, masked multi-head cross-attention with the extra ``beta`` column) with the *patches*
as the queries: a patch's query is encoded at its seed vertex (the generator of its geodesic
Voronoi cell, on the canonical shape), and its mask row is the handles' influence evaluated
at that seed (geodesic distance from the seed to each handle). The attended vector of each
patch goes through an output MLP that gives its B - 1 PBS weights:

- ``PerPatchPBS`` (the paper's section 4): P small zero-preserving MLPs, one per patch
  (stacked parameters, ``eqx.filter_vmap``), input multiplied by an affine map of the patch's
  base position (eq. 10's L_s at the patch: the layout-weighted mean of the base shape over
  the patch's vertices);
- ``BaseMultipliedPBS``: one shared zero-preserving MLP, the same multiplied input;
- ``NoModulationPBS``: one shared zero-preserving MLP on the attended vector alone.

These are Figure 8's three rows. Beyond the paper, ``local_prior`` (any variant, off by
default) adds the network's output to a per-patch least-squares fit of the basis to the
handles the patch sees (``local_pbs_fit``, weighted by the same clamped masks, with a trained
ridge), so the network learns the correction to a local blendshape fit; the last layer of the
output MLP starts at zero, so an untrained model *is* that fit. The fit is linear in the
displacements and zero where every mask is, so nothing below changes.

All stay zero-preserving: zero displacements give zero
weights, so the base shape exactly; a patch that every clamped mask misses gets zero weights,
so a vertex covered only by such patches does not move at all.

**Shape Transformer** (Chandran et al. 2022), the baseline of Tables 5 and 6: handle tokens
(Fourier-encoded canonical position and displacement) through a transformer encoder, then
each patch's query (its seed's position) cross-attends to the encoded tokens and an MLP
gives its weights. No base shape, no masks, not zero-preserving: it reconstructs relative to
the canonical shape only.
"""

from typing import ClassVar, Protocol, runtime_checkable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from ..canrig import influence_mask
from ..canrig._mlp import ZeroPreservingMLP
from ..canrig._model import ShapePreservingCANRig, _per_row
from ._basis import PatchLayout, _local_pbs_fit, _pbs_shape


def patch_means(layout: PatchLayout, points: Float[Array, "*B N 3"]) -> Float[Array, "*B P 3"]:
    """Each patch's layout-weighted mean of ``points`` over the vertices it covers."""
    vertex, patch, weight = layout.nonzero()
    p = layout.seeds.shape[0]
    mass = jax.ops.segment_sum(weight, patch, num_segments=p)

    def one(x):
        total = jax.ops.segment_sum(weight[:, None] * x[vertex], patch, num_segments=p)
        return total / jnp.maximum(mass, 1e-12)[:, None]

    lead = points.shape[:-2]
    flat = points.reshape(-1, *points.shape[-2:])
    return jax.vmap(one)(flat).reshape(*lead, p, 3)


@runtime_checkable
class PatchData(Protocol):
    """What a model's ``from_edit`` reads of its training set (a ``PBSTrainingSet``)."""

    @property
    def layout(self) -> PatchLayout: ...

    @property
    def neutral(self) -> Float[Array, "N 3"]: ...

    @property
    def basis(self) -> Float[Array, "Bm1 N 3"]: ...


class AbstractCANRigPBS(eqx.Module):
    """CANRig-PBS: masked cross-attention from handles to patches, PBS weights out. Its three
    final variants (Figure 8's rows) differ in the output head: ``PerPatchPBS`` (the paper's),
    ``BaseMultipliedPBS``, ``NoModulationPBS`` (module docstring).

    Attributes:
        encoder: the CANRig encoder (queries, keys, values, attention, base modulation); its
            per-vertex output MLP is unused and dropped (``None``).
        patch_mlp: the output MLP: one per patch (stacked, leading axis P) for
            ``PerPatchPBS``, else one shared.
        log_ridge: with ``local_prior``, log of the local fit's ridge (trained), else None.
    """

    encoder: eqx.AbstractVar[ShapePreservingCANRig]
    patch_mlp: eqx.AbstractVar[ZeroPreservingMLP]
    log_ridge: eqx.AbstractVar[Float[Array, ""] | None]

    per_patch: ClassVar[bool] = False
    """One output MLP per patch (stacked) instead of one shared."""
    base_modulated: ClassVar[bool] = True
    """The attended vector is multiplied by an affine map of the patch's base position."""

    def __init__(
        self,
        canonical: Float[ArrayLike, "V 3"],
        n_patches: int,
        n_weights: int,
        *,
        patch_width: int = 32,
        local_prior: bool = False,
        prior_ridge: float = 1e-2,
        key: PRNGKeyArray,
        **options,
    ):
        """``canonical`` (V, 3) the neutral (normalisation of positions); ``n_weights`` =
        B - 1 basis offsets; ``options``: the CANRig encoder's (``n_heads``, ``latent``,
        ``width``, ``n_layers``, ``fourier``, ``displacement_scale``); ``patch_width``: the
        hidden width of each per-patch MLP; ``local_prior``: add the network's output to
        ``local_pbs_fit`` with initial ridge ``prior_ridge`` (module docstring)."""
        if not (np.isfinite(prior_ridge) and prior_ridge > 0):
            raise ValueError(f"prior_ridge: expected a finite value > 0, got {prior_ridge}")
        for name, value in (("n_patches", n_patches), ("n_weights", n_weights)):
            if int(value) < 1:
                raise ValueError(f"{name}: expected >= 1, got {value}")
        ke, km = jax.random.split(key)
        encoder = ShapePreservingCANRig(canonical, key=ke, **options)
        self.encoder = eqx.tree_at(lambda m: m.output_mlp, encoder, None)
        arch = encoder.arch

        def output_mlp(width, key):
            return ZeroPreservingMLP(
                arch.latent,
                int(n_weights),
                width=width,
                n_layers=arch.n_layers,
                activation=jnp.tanh,
                key=key,
            )

        if self.per_patch:  # one per patch, parameters stacked on a leading axis
            keys = jax.random.split(km, int(n_patches))
            patch_mlp = eqx.filter_vmap(lambda k: output_mlp(patch_width, k))(keys)
        else:
            patch_mlp = output_mlp(arch.width, km)
        self.log_ridge = None
        if local_prior:  # the correction starts at zero: an untrained model is the local fit
            patch_mlp = eqx.tree_at(
                lambda m: m.layers[-1].weight, patch_mlp, replace_fn=jnp.zeros_like
            )
            self.log_ridge = jnp.log(jnp.asarray(prior_ridge, jnp.float32))
        self.patch_mlp = patch_mlp

    def from_edit(
        self,
        queries: Float[Array, "heads P d"],
        data: PatchData,
        handle_vertices: Int[Array, " H"],
        handle_distance: Float[Array, "P H"],
        base: Float[Array, "N 3"],
        displacements: Float[Array, "H 3"],
        radius: float | Float[ArrayLike, ""],
        falloff: float | Float[ArrayLike, ""],
        patch_base: Float[Array, "P 3"] | None = None,
    ) -> Float[Array, "P Bm1"]:
        """S_pred for one training-style edit (``predict_pbs_weights``): ``data`` a
        ``PBSTrainingSet`` (layout, basis, neutral), one radius and falloff for every handle,
        ``handle_distance`` from each patch's seed to each handle."""
        if patch_base is None:
            patch_base = patch_means(data.layout, base)
        mask = influence_mask(handle_distance, radius, falloff)
        return self(
            queries,
            patch_base,
            data.neutral[handle_vertices],
            base[handle_vertices],
            displacements,
            mask,
            handle_basis=data.basis[:, handle_vertices] if self.local_prior else None,
        )

    @property
    def local_prior(self) -> bool:
        return self.log_ridge is not None

    def encode_patches(self, seeds_canonical: Float[Array, "P 3"]) -> Float[Array, "heads P d"]:
        """Queries of the patches at their seeds' canonical positions; cache these."""
        return self.encoder.encode_queries(seeds_canonical)

    def __call__(
        self,
        patch_queries: Float[Array, "heads P d"],
        patch_base: Float[Array, "P 3"],
        handle_canonical: Float[Array, "H 3"],
        handle_base: Float[Array, "H 3"],
        displacements: Float[Array, "H 3"],
        mask: Float[Array, "P H"],
        beta: float | Float[Array, ""] | None = None,
        handle_basis: Float[Array, "Bm1 H 3"] | None = None,
    ) -> Float[Array, "P Bm1"]:
        """S_pred, the PBS weights of each patch (a delta over the base shape's).

        ``patch_base``: ``patch_means(layout, base)``; ``mask``: the handles' influence at
        each patch's seed (``influence_mask``), clamped here; ``handle_basis``: the basis
        offsets at the handle vertices, required by a ``local_prior`` model."""
        log_ridge = self.log_ridge
        if log_ridge is not None and handle_basis is None:
            raise ValueError("handle_basis: required by a local_prior model, got None")
        enc = self.encoder
        keys = enc.encode_keys(handle_canonical)
        values = enc.encode_values(displacements, handle_base)
        attention = enc.attention(patch_queries, keys, mask, beta)
        attended = enc.merge_heads(jnp.matmul(attention, values))  # (P, latent)
        if self.base_modulated:
            attended = attended * _per_row(enc.output_modulation, enc.normalise(patch_base))
        if self.per_patch:
            out = eqx.filter_vmap(lambda mlp, x: mlp(x))(self.patch_mlp, attended)
        else:
            out = _per_row(self.patch_mlp, attended)
        if log_ridge is None or handle_basis is None:  # not a local_prior model
            return out
        clamped = jnp.where(mask < enc.clamp, 0.0, mask)
        return out + _local_pbs_fit(handle_basis, displacements, clamped, jnp.exp(log_ridge))


class PerPatchPBS(AbstractCANRigPBS):
    """CANRig-PBS as in the paper (section 4): one small zero-preserving MLP per patch, its
    input multiplied by an affine map of the patch's base position."""

    encoder: ShapePreservingCANRig
    patch_mlp: ZeroPreservingMLP
    log_ridge: Float[Array, ""] | None

    per_patch: ClassVar[bool] = True


class BaseMultipliedPBS(AbstractCANRigPBS):
    """Figure 8's middle row: one shared output MLP, the same base-multiplied input."""

    encoder: ShapePreservingCANRig
    patch_mlp: ZeroPreservingMLP
    log_ridge: Float[Array, ""] | None


class NoModulationPBS(AbstractCANRigPBS):
    """Figure 8's last row: one shared output MLP on the attended vector alone."""

    encoder: ShapePreservingCANRig
    patch_mlp: ZeroPreservingMLP
    log_ridge: Float[Array, ""] | None

    base_modulated: ClassVar[bool] = False


PBS_VARIANTS = {
    "per_patch": PerPatchPBS,
    "base_multiplied": BaseMultipliedPBS,
    "no_modulation": NoModulationPBS,
}
"""CANRig-PBS variants by the name a training option or command line gives (Figure 8's
ablation); ``per_patch`` is the paper's model."""


class _EncoderBlock(eqx.Module):
    attention: eqx.nn.MultiheadAttention
    mlp: eqx.nn.MLP
    norm1: eqx.nn.LayerNorm
    norm2: eqx.nn.LayerNorm

    def __init__(self, size: int, n_heads: int, width: int, key: PRNGKeyArray):
        ka, km = jax.random.split(key)
        self.attention = eqx.nn.MultiheadAttention(n_heads, size, key=ka)
        self.mlp = eqx.nn.MLP(size, size, width, 1, activation=jax.nn.gelu, key=km)
        self.norm1 = eqx.nn.LayerNorm(size)
        self.norm2 = eqx.nn.LayerNorm(size)

    def __call__(self, x: Float[Array, "H size"]) -> Float[Array, "H size"]:
        y = jax.vmap(self.norm1)(x)
        x = x + self.attention(y, y, y)
        return x + jax.vmap(self.mlp)(jax.vmap(self.norm2)(x))


class ShapeTransformer(eqx.Module):
    """The Shape Transformer baseline: a transformer encoder over handle tokens and a
    cross-attention decoder queried per patch; PBS weights out (relative to the canonical
    shape: no base shape, no masks)."""

    centre: tuple[float, float, float] = eqx.field(static=True)
    position_scale: float = eqx.field(static=True)
    displacement_scale: float = eqx.field(static=True)
    fourier: int = eqx.field(static=True)
    token: eqx.nn.MLP
    blocks: tuple[_EncoderBlock, ...]
    query: eqx.nn.MLP
    cross: eqx.nn.MultiheadAttention
    head: eqx.nn.MLP

    def __init__(
        self,
        canonical: Float[ArrayLike, "V 3"],
        n_weights: int,
        *,
        latent: int = 64,
        n_heads: int = 4,
        width: int = 128,
        n_layers: int = 2,
        fourier: int = 6,
        displacement_scale: float = 1.0,
        key: PRNGKeyArray,
    ):
        canonical = np.asarray(canonical, np.float64)
        if canonical.ndim != 2 or canonical.shape[1] != 3:
            raise ValueError(f"canonical: expected shape (V, 3), got {canonical.shape}")
        if latent % n_heads:
            raise ValueError(f"latent: expected a multiple of n_heads={n_heads}, got {latent}")
        centre = canonical.mean(axis=0)
        self.centre = (float(centre[0]), float(centre[1]), float(centre[2]))
        self.position_scale = float(np.sqrt(((canonical - centre) ** 2).sum(axis=1).mean()))
        self.displacement_scale = float(displacement_scale)
        self.fourier = int(fourier)
        n_position = 3 + 6 * self.fourier
        kt, kb, kq, kc, kh = jax.random.split(key, 5)
        self.token = eqx.nn.MLP(n_position + 3, latent, width, 1, activation=jax.nn.gelu, key=kt)
        self.blocks = tuple(
            _EncoderBlock(latent, n_heads, width, k) for k in jax.random.split(kb, n_layers)
        )
        self.query = eqx.nn.MLP(n_position, latent, width, 1, activation=jax.nn.gelu, key=kq)
        self.cross = eqx.nn.MultiheadAttention(n_heads, latent, key=kc)
        self.head = eqx.nn.MLP(latent, int(n_weights), width, 1, activation=jax.nn.gelu, key=kh)

    def encode_position(self, points: Float[Array, "N 3"]) -> Float[Array, "N F"]:
        x = (points - jnp.asarray(self.centre, points.dtype)) / self.position_scale
        if not self.fourier:
            return x
        frequencies = jnp.pi * 2.0 ** jnp.arange(self.fourier, dtype=x.dtype)
        angles = (x[..., None] * frequencies).reshape(*x.shape[:-1], -1)
        return jnp.concatenate([x, jnp.sin(angles), jnp.cos(angles)], axis=-1)

    def encode_patches(self, seeds_canonical: Float[Array, "P 3"]) -> Float[Array, "P latent"]:
        return jax.vmap(self.query)(self.encode_position(seeds_canonical))

    def from_edit(
        self,
        queries: Float[Array, "P latent"],
        data: PatchData,
        handle_vertices: Int[Array, " H"],
        handle_distance: Float[Array, "P H"],
        base: Float[Array, "N 3"],
        displacements: Float[Array, "H 3"],
        radius: float | Float[ArrayLike, ""],
        falloff: float | Float[ArrayLike, ""],
        patch_base: Float[Array, "P 3"] | None = None,
    ) -> Float[Array, "P Bm1"]:
        """S_pred for one training-style edit: the baseline ignores the base, masks and
        radius (relative to the canonical shape)."""
        del handle_distance, base, radius, falloff, patch_base
        return self(queries, data.neutral[handle_vertices], displacements)

    def __call__(
        self,
        patch_queries: Float[Array, "P latent"],
        handle_canonical: Float[Array, "H 3"],
        displacements: Float[Array, "H 3"],
    ) -> Float[Array, "P Bm1"]:
        tokens = jnp.concatenate(
            [self.encode_position(handle_canonical), displacements / self.displacement_scale],
            axis=-1,
        )
        x = jax.vmap(self.token)(tokens)
        for block in self.blocks:
            x = block(x)
        attended = self.cross(patch_queries, x, x)
        return jax.vmap(self.head)(attended)


def pbs_delta_shape(
    layout: PatchLayout,
    base: Float[Array, "N 3"],
    basis: Float[Array, "Bm1 N 3"],
    weights: Float[Array, "P Bm1"],
) -> Float[Array, "N 3"]:
    """S = S_base + W_layout S_pred S_basis (eq. 7 with the base in place of the neutral):
    zero weights give the base exactly. jit/vmap-able (the validated form is ``pbs_shape``)."""
    return _pbs_shape(layout, base, basis, weights)
