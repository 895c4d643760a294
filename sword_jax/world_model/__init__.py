"""sword_jax.world_model."""
