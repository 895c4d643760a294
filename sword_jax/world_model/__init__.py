"""sword_jax.world_model: flow matching, sampling, rollouts, data and the train step of the world model.

Modules (import them directly; importing this package has no side effects):

* ``flow``: Wan's shifted flow-matching schedule, noising, velocity/epsilon targets, loss.
* ``sampler``: shifted Euler sampler (one ``lax.scan``) with optional action guidance.
* ``rollout``: autoregressive latent rollouts (one jit), WoVR pixel round trip, streaming decode.
* ``data``: the pre-encoded latent dataset, the resumable segment sampler and sharded loader.
* ``train_state`` / ``train_step``: the pure ``step(state, batch, key)`` (teacher forcing or DLB).
* ``cache_fidelity``: what DLB writes into its cache and how far that is from inference's context.

The model itself is :mod:`sword_jax.dit.action_dit`; checkpoints and metric logging, shared by every
trainer, are :mod:`sword_jax.checkpoint`.
"""
