"""sword_jax.augment."""
