"""sword_jax.dit."""
