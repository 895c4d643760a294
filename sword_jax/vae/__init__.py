"""sword_jax.vae."""
