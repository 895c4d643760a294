"""sword_jax.convert."""
