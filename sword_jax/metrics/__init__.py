"""sword_jax.metrics."""
