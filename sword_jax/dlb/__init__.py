"""sword_jax.dlb: Dynamic Latent Bootstrapping.

* ``cache``: the device-resident latent cache (layout, sharding, bytes per device, read, write).
* ``schedule``: read-probability schedules (linear, warmup + cosine).
* ``config``: ``CacheConfig``.

What the cache is written with (``one_step`` / ``sampler``) and its distance from the context
inference produces is :mod:`sword_jax.world_model.cache_fidelity` (it runs the world model's sampler;
this package holds no model code). The DLB train step itself is :func:`sword_jax.world_model.train_step.make_train_step` with
``cache.enabled``.
"""
