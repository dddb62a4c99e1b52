"""Masked multi-head cross-attention against a NumPy reference, stability, empty rows."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from canrig_jax.canrig._attention import masked_cross_attention


def _reference(q, k, v, mask, beta):
    """Loops over heads and vertices, float64: exp(A) M / (sum exp(A) M [+ exp(beta)])."""
    heads, n_v, d = q.shape
    out = np.zeros((heads, n_v, v.shape[-1]))
    for n in range(heads):
        for i in range(n_v):
            logits = k[n] @ q[n, i] / np.sqrt(d)
            shift = max(
                [logits[h] for h in range(len(logits)) if mask[i, h] > 0] + [beta or -np.inf]
            )
            if not np.isfinite(shift):
                continue
            num = np.exp(logits - shift) * mask[i]
            den = num.sum() + (np.exp(beta - shift) if beta is not None else 0.0)
            if den > 0:
                out[n, i] = num @ v[n] / den
    return out


@pytest.mark.parametrize("beta", [None, 0.0, 2.5])
@pytest.mark.parametrize("scale", [1.0, 300.0])
def test_against_numpy_reference(beta, scale):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(3, 7, 4)) * scale
    k = rng.normal(size=(3, 5, 4))
    v = rng.normal(size=(3, 5, 2))
    mask = rng.uniform(size=(7, 5)) * (rng.uniform(size=(7, 5)) < 0.5)
    mask[2] = 0.0  # a vertex no handle influences
    args = (jnp.asarray(a, jnp.float32) for a in (q, k, v, mask))
    got = jax.jit(masked_cross_attention)(*args, beta)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, _reference(q, k, v, mask, beta), rtol=2e-4, atol=2e-5)
    assert np.all(np.asarray(got)[:, 2] == 0.0)


def test_no_influence_is_defined_and_differentiable():
    rng = np.random.default_rng(1)
    q, k, v = (
        jnp.asarray(rng.normal(size=s), jnp.float32) for s in ((2, 4, 3), (2, 6, 3), (2, 6, 3))
    )
    mask = jnp.zeros((4, 6)).at[0, 1].set(0.7)

    def loss(q, k, v):
        return jnp.sum(masked_cross_attention(q, k, v, mask) ** 2)

    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(q, k, v)
    assert all(bool(jnp.all(jnp.isfinite(g))) for g in grads)
    out = jax.jit(masked_cross_attention)(q, k, v, mask)
    assert np.all(np.asarray(out)[:, 1:] == 0.0)
    # one influencing handle takes all the weight without beta
    np.testing.assert_allclose(out[:, 0], v[:, 1], rtol=1e-6)
