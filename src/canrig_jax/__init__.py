"""canrig_jax: differentiable face rigs in JAX on real assets."""

__version__ = "0.1.0"
