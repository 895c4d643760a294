"""sword_jax.rl."""
