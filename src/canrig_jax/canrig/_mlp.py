"""Zero-preserving MLPs (CANRig appendix B): no biases and activations with a(0) = 0, so a
zero input gives an exactly zero output; the rig then reproduces the base shape exactly when
every handle displacement is zero."""

from collections.abc import Callable

import equinox as eqx
import jax
from jaxtyping import Array, Float, PRNGKeyArray


class ZeroPreservingMLP(eqx.Module):
    """``n_layers`` bias-free linear layers with ``activation`` between them (none after the
    last), and optionally a bias-free linear skip from input to output (``linear_skip``).
    f(0) = 0 exactly for any weights, provided activation(0) == 0."""

    layers: tuple[eqx.nn.Linear, ...]
    activation: Callable[[Float[Array, "*shape"]], Float[Array, "*shape"]] = eqx.field(static=True)
    skip: eqx.nn.Linear | None = None

    def __init__(
        self,
        in_size: int,
        out_size: int,
        *,
        width: int = 64,
        n_layers: int = 3,
        activation: Callable[[Float[Array, "*shape"]], Float[Array, "*shape"]] = jax.nn.gelu,
        linear_skip: bool = False,
        key: PRNGKeyArray,
    ):
        if n_layers < 1:
            raise ValueError(f"n_layers: expected >= 1, got {n_layers}")
        if float(activation(jax.numpy.zeros(()))) != 0.0:
            raise ValueError("activation: expected activation(0) == 0 to preserve zero")
        sizes = [in_size] + [width] * (n_layers - 1) + [out_size]
        if linear_skip:
            key, skip_key = jax.random.split(key)
            self.skip = eqx.nn.Linear(in_size, out_size, use_bias=False, key=skip_key)
        keys = jax.random.split(key, n_layers)
        self.layers = tuple(
            eqx.nn.Linear(a, b, use_bias=False, key=k)
            for a, b, k in zip(sizes[:-1], sizes[1:], keys, strict=True)
        )
        self.activation = activation

    def __call__(self, x: Float[Array, " in_size"]) -> Float[Array, " out_size"]:
        y = x
        for layer in self.layers[:-1]:
            y = self.activation(layer(y))
        y = self.layers[-1](y)
        return y if self.skip is None else y + self.skip(x)
