"""sword_jax.dlb."""
