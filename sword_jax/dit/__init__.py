"""sword_jax.dit: the Wan 2.2 TI2V diffusion transformer and the action-conditioned world model.

Modules:
  ``config``: :class:`DiTConfig` (the ``model`` config section).
  ``layers``: linear layers with logical axes, norms, timestep sinusoid, 3D RoPE, attention.
  ``model``: :class:`WanDiT`, the official ``WanModel`` (TI2V) port.
  ``action_dit``: :class:`WorldModel` (WanDiT + action cross-attention tokens + action AdaLN),
  ``world_model_apply``. Its training (flow, sampler, rollouts, data, train step) is
  :mod:`sword_jax.world_model`.

Official checkpoints are read by :mod:`sword_jax.convert` (``wan22_dit.load_official`` and
``wan22_dit.load_official_into_world_model``); this package does not import it.
"""
