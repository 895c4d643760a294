"""sword_jax.rl: GRPO post-training of a VLA policy inside the learned simulator.

Modules: ``config`` (RLConfig), ``policy`` (VLAPolicy, byte-level instructions, 256-bin action
chunks), ``learned_simulator`` (LearnedSimulator / RewardModel protocols, toy world), ``world_model_sim``
(WorldModel + streaming VAE as a LearnedSimulator), ``rollout`` (imagined rollouts, one jit),
``grpo`` (advantages, clipped loss, jitted update), ``sft`` (behaviour cloning), ``reward_model``
(success detector), ``data`` (episodes and samplers), ``env`` (brax and gymnasium envs),
``policy_success`` (success in the ground-truth MuJoCo environments and the curve), ``params_io``
(checkpoints). The ground-truth environments themselves are the top-level ``sim`` package.
"""
