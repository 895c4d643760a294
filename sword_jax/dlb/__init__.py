"""sword_jax.dlb: Dynamic Latent Bootstrapping.

* ``cache``: the device-resident latent cache (layout, sharding, bytes per device, read, write).
* ``schedule``: read-probability schedules (linear, warmup + cosine).
* ``config``: ``CacheConfig``.

The DLB train step itself is :func:`sword_jax.world_model.train_step.make_train_step` with
``cache.enabled``.
"""
