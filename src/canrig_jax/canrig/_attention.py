"""Masked multi-head cross-attention (CANRig eq. 2 and eq. 10).

Vertices (queries) attend to handles (keys, values). The influence mask M multiplies the
softmax numerator, A_M = exp(A) M / sum_h exp(A_h) M_h, so a handle outside a vertex's region
contributes nothing. Optionally an extra column with logit ``beta``, mask 1 and a zero value
(section 3.2) takes the weight the handles do not: a vertex no handle influences then gets
exactly zero, and near the region's border the edit fades out smoothly.

Computed as a softmax of A + log M (log 0 = -inf), which is the same expression, with the row
maximum over the influencing handles (and beta) subtracted before exponentiating, so it is
numerically stable for any logit size. Defined everywhere: a row without any influencing
handle (and no beta column) gets weight 0 on every handle, not 0/0.

Layout is heads-first, (heads, V, d), so both products are batched matrix multiplies.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._layout import Local


def masked_attention_weights(
    logits: Float[Array, "*lead V H"],
    mask: Float[Array, "*#lead V H"],
    beta: float | Float[Array, ""] | None = None,
) -> tuple[Float[Array, "*lead V H"], Float[Array, "*lead V 1"]]:
    """Unnormalised weights w = exp(A + log M - m) and their normaliser
    sum_h w_h [+ exp(beta - m)] (1 where the row has no weight at all), with m the row max
    of A + log M (and beta). The attention weights are w / normaliser. ``mask`` broadcasts
    against the leading (heads, batch) axes of ``logits``."""
    influenced = mask > 0
    log_mask = jnp.where(influenced, jnp.log(jnp.where(influenced, mask, 1.0)), -jnp.inf)
    scores = jnp.where(influenced, logits, 0.0) + log_mask
    row_max = jnp.max(scores, axis=-1, keepdims=True)
    if beta is not None:
        row_max = jnp.maximum(row_max, beta)
    row_max = jnp.where(jnp.isfinite(row_max), row_max, 0.0)
    weights = jnp.exp(scores - row_max)
    normaliser = jnp.sum(weights, axis=-1, keepdims=True)
    if beta is not None:
        normaliser = normaliser + jnp.exp(beta - row_max)
    return weights, jnp.where(normaliser > 0, normaliser, 1.0)


def masked_cross_attention(
    queries: Float[Array, "heads V d"],
    keys: Float[Array, "heads H d"],
    values: Float[Array, "heads H e"],
    mask: Float[Array, "V H"],
    beta: float | Float[Array, ""] | None = None,
) -> Float[Array, "heads V e"]:
    """Multi-head masked cross-attention: logits q.k / sqrt(d) per head, one mask shared by
    all heads, the weighted sum of values (see ``masked_attention_weights``)."""
    scale = 1.0 / jnp.sqrt(jnp.asarray(queries.shape[-1], queries.dtype))
    logits = jnp.matmul(queries, jnp.swapaxes(keys, -1, -2)) * scale
    weights, normaliser = masked_attention_weights(logits, mask, beta)
    return jnp.matmul(weights, values) / normaliser


class Trace(eqx.Module):
    """One forward pass with its intermediates: the shape (N, 3), the attended vectors
    (N, latent) in vertex order, and the attention weights (heads, ...) in the layout's local
    form (a tuple of them for a ``PartsLayout``; they do not depend on the displacements)."""

    shape: Float[Array, "N 3"]
    attended: Float[Array, "N latent"]
    attention: Local
