"""Zero-preserving MLPs: f(0) == 0 exactly for any weights (hypothesis)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canrig_jax.canrig._mlp import ZeroPreservingMLP


@settings(max_examples=3, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    sizes=st.tuples(st.integers(1, 9), st.integers(1, 9), st.integers(1, 33), st.integers(1, 4)),
    activation=st.sampled_from([jax.nn.gelu, jnp.tanh]),
)
def test_zero_in_zero_out(seed, sizes, activation):
    in_size, out_size, width, n_layers = sizes
    mlp = ZeroPreservingMLP(
        in_size,
        out_size,
        width=width,
        n_layers=n_layers,
        activation=activation,
        key=jax.random.PRNGKey(seed),
    )
    out = eqx.filter_jit(lambda m, x: m(x))(mlp, jnp.zeros(in_size))
    assert out.shape == (out_size,)
    assert bool(jnp.all(out == 0.0))
    assert all(layer.bias is None for layer in mlp.layers)


def test_rejects_activation_without_zero():
    with pytest.raises(ValueError, match="activation"):
        ZeroPreservingMLP(3, 3, activation=jax.nn.sigmoid, key=jax.random.PRNGKey(0))
