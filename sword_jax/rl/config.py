"""RL section of the experiment config (owned by sword_jax.rl)."""

import dataclasses


@dataclasses.dataclass(frozen=True)
class RLConfig:
    """Policy, reward model and GRPO settings.

    Attributes:
      group_size: G, trajectories sampled per start state (GRPO group).
      clip_low / clip_high: PPO ratio clip range ``[1 - clip_low, 1 + clip_high]`` (DAPO clip-higher).
      kl_coef: weight of the k3 KL estimate to the reference (SFT) policy; 0 = off.
      learning_rate: GRPO learning rate.
      grpo_steps: GRPO updates per run.
      ppo_epochs: gradient steps per batch of imagined rollouts (1 = on-policy GRPO).
      max_chunks: step limit of an imagined rollout, in action chunks.
      chunk_len: actions per chunk (= frames the simulator predicts per step).
      action_dim: action dimensions (xyz, rotation, gripper).
      action_bins: discretisation bins per action dimension (OpenVLA: 256).
      success_threshold: reward-model score that counts as success (WoVR: 0.9).
      filter_groups: drop groups whose rewards are all equal (no learning signal).
      success_bonus: added to a trajectory's return when it reaches success.
      imagined_return: the return of an imagined trajectory. ``success`` (default): ``1 +
        success_bonus`` on success, else 0, the same return GRPO in the ground-truth environments
        uses (where the update was validated: +16.4 points on `small`), so a group whose
        trajectories all fail carries no signal and is filtered. ``score``: the summed per-chunk
        changes of the detector's score plus the bonus on success (the earlier rule): every
        group then has a spread, and failing groups are ranked by the detector's score on frames
        that are not successes, a signal GRPO can climb without succeeding.
      loss_norm: 'trajectory' averages token losses within each trajectory (normalising by its
        length) and then over trajectories (GRPO); 'token' averages over all valid tokens (DAPO).
      temperature: sampling temperature of the policy during rollouts.
      sft_steps / sft_batch_size / sft_learning_rate / sft_episodes_per_task: behaviour cloning knobs
        (steps and number of demonstrations set how good the starting policy is).
      reward_model_steps / reward_model_batch_size / reward_model_learning_rate: success detector.
      positive_tail: the last this-many frames of a successful episode are positives
        (``reward_labels=tail``).
      reward_labels: what the success detector learns. ``state`` (default): the task's success
        predicate on the state each frame shows (the simulator's per-step success), over whole
        episodes, so frames after success (bowl resting on the plate, the arm retreating) are
        positives and frames with the bowl lifted off again negatives. ``tail``: the last
        ``positive_tail`` frames of successful episodes read up to their first success, i.e. the
        frames just *before* the bowl lands (the earlier recipe; see README for what it measured).
      policy_width: base width of the policy (image encoder channels, token width).
      policy_layers: transformer layers of the instruction / fusion encoder.
      policy_heads: attention heads of the policy transformer.
      max_instruction_bytes: byte-level instruction tokens (padded / truncated).
      image_size: frame size the policy and reward model see (frames are resized to it).
      proprio_dim: proprioceptive state dimensions the environment reports (0 = none).
      proprio_encoding: 'rot6d' turns the simulator's 8-D proprio (xyz, axis-angle, fingers) into
        continuous features (the axis-angle becomes two rotation-matrix columns); 'raw' uses it as is.
      execute_steps: actions of each predicted chunk executed before the policy re-plans
        (``chunk_len`` = open-loop chunks; 1 = re-plan every step).
      action_ensemble: ACT-style temporal ensembling when re-planning every step: each step of a
        greedy (evaluation) rollout executes the exponentially weighted mean of every chunk's
        prediction for it; sampled GRPO rollouts in the real environments re-plan every step.
        Measured on `small` (README): ensembling 0.715, every step 0.690, every 2 actions 0.490,
        every 4 0.350, open-loop 8 0.192.
      imagined_execute_steps: actions of each chunk executed inside the learned simulator before
        the policy re-plans: a multiple of 4 (the world model's latent frame) dividing ``chunk_len``.
        None (default) = ``chunk_len``, whole chunks (one world-model call per chunk); 4 = the world model still
        predicts the chunk's frames from all its actions, keeps the first latent's 4 frames and the
        policy re-plans from the last of them (twice the world-model calls per action). ``max_chunks``
        counts policy decisions either way.
      imagined_proprio: what the policy reads as proprio inside the learned simulator, which predicts
        frames only. ``missing`` (default): the policy's learned "missing proprio" input, a mode SFT
        trains by proprio dropout. ``reckoned``: integrated from the start state's proprio and the
        executed actions by the controller's action convention (:mod:`sword_jax.rl.proprio_reckoning`).
        Measured on `small` in the real environments (README), the SFT policy succeeds 0.265 with true
        proprio, 0.200 with it missing and 0.160 with it reckoned (200 episodes each): the reckoning's
        drift (2.4 cm after 8 actions, 5.4 cm after 32) misleads the policy more than no proprio does.
        Either way the imagined mode is not the true-proprio mode, hence ``eval_masked_proprio``.
      eval_masked_proprio: every real-environment evaluation of GRPO in the learned simulator also
        runs the policy with proprio masked (its "missing proprio" input mode; one more evaluation
        each), stored as ``proprio_masked`` in the success curve: with ``imagined_proprio=missing``
        that is the mode GRPO trained, so it measures the update free of the input-mode shift, and
        the true-proprio curve beside it measures how much of it carries over. On by default.
      eval_replay_episodes: at every real-environment evaluation of GRPO in the learned simulator,
        this many of the evaluated episodes (spread over the tasks) are replayed in the learned
        simulator: their executed actions, open loop, from the same start (frame 4 k, the real
        history before it), scored by the success detector (:mod:`sword_jax.rl.sim_agreement`).
        Stored as ``replay`` in the success curve: how often the simulator calls a real failure a
        success (``false_success``, what GRPO can exploit) or misses a real success. 0 = off.
      env_proprio: what the policy reads as proprio in GRPO rollouts in the ground-truth environments
        (``train.grpo --simulator env``): ``true`` (default), the environment's; ``reckoned``, dead-reckoned
        from the executed actions as the learned simulator does (``imagined_proprio=reckoned``);
        ``missing``, the "missing proprio" input (``imagined_proprio=missing``). The environment and
        reward stay true, so a GRPO run in it isolates the input mode from world-model error; every
        evaluation then also measures that mode beside the true-proprio success.
      env_starts: where GRPO rollouts in the ground-truth environments start. ``initial`` (default):
        training-split initial states at rest, for ``sim.max_steps``. ``keyframes``: the
        demonstrations' recorded states at the keyframes GRPO in the learned simulator starts from
        (the first half of each, latent-aligned: :func:`sword_jax.rl.data.keyframe_starts`), for the
        learned simulator's horizon (``max_chunks`` decisions of ``imagined_execute_steps or
        chunk_len`` actions, executed as it executes them; evaluations keep ``execute_steps``). With
        ``env_proprio=missing``, GRPO in the real environments then has the learned simulator's
        setting with true dynamics and true success: whether that setting can lift success from
        rest, free of world-model error.
      update_microbatch: trajectories per forward/backward pass of the GRPO update (0 = the whole
        batch at once); gradients are summed over the micro-batches, so the update is the same up to
        float summation order while activation memory falls by batch / micro-batch (the whole
        ``small`` batch, 64 trajectories x 55 decisions, asked for 47 GiB at once on an H100).
      ensemble_decay: weight ``exp(-decay * age)`` of a prediction made ``age`` steps ago.
      sft_lr_end_fraction: the SFT cosine schedule ends at this fraction of its peak.
      sft_warmup_steps: linear warm-up of the SFT learning rate.
      sft_eval_every: SFT steps between teacher-forced metrics on held-out demonstrations.
      sft_checkpoint_every / reward_model_checkpoint_every: steps between the train-state
        checkpoints an SFT / reward-model run resumes from (``train.train_policy`` /
        ``train.train_reward``; the last step is always saved).
      reward_width: base channels of the success-detector CNN.
      eval_every: GRPO steps between ground-truth evaluations.
      eval_episodes_per_task: initial states per task in ground-truth evaluation (paper: 50).
      rollout_batch: start states per GRPO step (each expanded to ``group_size`` trajectories).
    """

    group_size: int = 8
    clip_low: float = 0.2
    clip_high: float = 0.28
    kl_coef: float = 0.0
    learning_rate: float = 1e-5
    grpo_steps: int = 10
    ppo_epochs: int = 1
    max_chunks: int = 8
    chunk_len: int = 8
    action_dim: int = 7
    action_bins: int = 256
    success_threshold: float = 0.9
    filter_groups: bool = True
    success_bonus: float = 1.0
    imagined_return: str = "success"  # success | score
    loss_norm: str = "trajectory"  # trajectory | token
    temperature: float = 1.0
    sft_steps: int = 200
    sft_batch_size: int = 32
    sft_learning_rate: float = 3e-4
    sft_episodes_per_task: int = 0  # 0 = all available demonstrations
    reward_model_steps: int = 200
    reward_model_batch_size: int = 32
    reward_model_learning_rate: float = 1e-3
    positive_tail: int = 8
    reward_labels: str = "state"  # state | tail
    policy_width: int = 64
    policy_layers: int = 2
    policy_heads: int = 4
    max_instruction_bytes: int = 96
    image_size: int = 64
    proprio_dim: int = 8
    proprio_encoding: str = "rot6d"  # rot6d | raw
    execute_steps: int = 1
    action_ensemble: bool = True
    imagined_execute_steps: int | None = None  # None = chunk_len (whole chunks)
    imagined_proprio: str = "missing"  # missing | reckoned
    eval_masked_proprio: bool = True  # also evaluate GRPO-in-the-world-model policies with proprio masked
    eval_replay_episodes: int = 100  # real evaluation episodes replayed in the learned simulator; 0 = off
    env_proprio: str = "true"  # true | reckoned | missing: the policy's proprio in ground-truth GRPO rollouts
    env_starts: str = "initial"  # initial | keyframes: where ground-truth GRPO rollouts start
    update_microbatch: int = 0  # trajectories per forward/backward of the GRPO update; 0 = all
    ensemble_decay: float = 0.1
    sft_lr_end_fraction: float = 0.1
    sft_warmup_steps: int = 50
    sft_eval_every: int = 100
    sft_checkpoint_every: int = 100
    reward_model_checkpoint_every: int = 100
    reward_width: int = 16
    eval_every: int = 5
    eval_episodes_per_task: int = 50
    rollout_batch: int = 4

    def validate(self) -> None:
        if self.group_size < 2:
            raise ValueError(f"rl.group_size must be >= 2 for group-normalised advantages, got {self.group_size}")
        if not 0.0 < self.success_threshold <= 1.0:
            raise ValueError(f"rl.success_threshold must be in (0, 1], got {self.success_threshold}")
        if not 0.0 <= self.clip_low < 1.0 or self.clip_high < 0.0:
            raise ValueError(f"rl.clip_low must be in [0, 1) and clip_high >= 0, got {self.clip_low}/{self.clip_high}")
        if self.kl_coef < 0.0:
            raise ValueError(f"rl.kl_coef must be >= 0, got {self.kl_coef}")
        if self.action_bins < 2:
            raise ValueError(f"rl.action_bins must be >= 2, got {self.action_bins}")
        if self.max_chunks < 1 or self.chunk_len < 1 or self.ppo_epochs < 1:
            raise ValueError(
                f"rl.max_chunks/chunk_len/ppo_epochs must be >= 1, got {self.max_chunks}/{self.chunk_len}/{self.ppo_epochs}"
            )
        if self.policy_width % self.policy_heads:
            raise ValueError(f"rl.policy_heads={self.policy_heads} must divide policy_width={self.policy_width}")
        if self.image_size % 8:
            raise ValueError(f"rl.image_size must be a multiple of 8 (three stride-2 convs), got {self.image_size}")
        if self.temperature <= 0.0:
            raise ValueError(f"rl.temperature must be > 0, got {self.temperature}")
        if self.loss_norm not in ("trajectory", "token"):
            raise ValueError(f"rl.loss_norm must be trajectory|token, got {self.loss_norm!r}")
        if self.proprio_encoding not in ("rot6d", "raw"):
            raise ValueError(f"rl.proprio_encoding must be rot6d|raw, got {self.proprio_encoding!r}")
        if self.proprio_encoding == "rot6d" and self.proprio_dim != 8:
            raise ValueError(f"rl.proprio_encoding=rot6d reads the simulator's 8-D proprio; got proprio_dim="
                             f"{self.proprio_dim} (use proprio_encoding=raw)")
        if not 1 <= self.execute_steps <= self.chunk_len:
            raise ValueError(f"rl.execute_steps must be in [1, chunk_len={self.chunk_len}], got {self.execute_steps}")
        if self.imagined_execute_steps is not None and (
                self.imagined_execute_steps < 4 or self.imagined_execute_steps % 4
                or self.chunk_len % self.imagined_execute_steps):
            raise ValueError(f"rl.imagined_execute_steps must be a multiple of 4 (one latent frame) dividing "
                             f"rl.chunk_len={self.chunk_len}, got {self.imagined_execute_steps}")
        if self.imagined_proprio not in ("reckoned", "missing"):
            raise ValueError(f"rl.imagined_proprio must be reckoned|missing, got {self.imagined_proprio!r}")
        if self.update_microbatch < 0:
            raise ValueError(f"rl.update_microbatch must be >= 0 (0 = the whole batch), got {self.update_microbatch}")
        if self.update_microbatch and (self.rollout_batch * self.group_size) % self.update_microbatch:
            raise ValueError(f"rl.update_microbatch={self.update_microbatch} must divide rl.rollout_batch x "
                             f"rl.group_size = {self.rollout_batch * self.group_size}")
        if self.env_proprio not in ("true", "reckoned", "missing"):
            raise ValueError(f"rl.env_proprio must be true|reckoned|missing, got {self.env_proprio!r}")
        if self.env_proprio == "reckoned" and self.proprio_dim != 8:
            raise ValueError(f"rl.env_proprio=reckoned integrates the simulator's 8-D proprio; got rl.proprio_dim="
                             f"{self.proprio_dim}")
        if self.action_ensemble and self.execute_steps != 1:
            raise ValueError(f"rl.action_ensemble needs rl.execute_steps=1 (a new chunk every step), got "
                             f"execute_steps={self.execute_steps}: set rl.action_ensemble=false to execute "
                             f"{self.execute_steps} actions per chunk")
        if self.ensemble_decay < 0.0:
            raise ValueError(f"rl.ensemble_decay must be >= 0, got {self.ensemble_decay}")
        if not 0.0 <= self.sft_lr_end_fraction <= 1.0:
            raise ValueError(f"rl.sft_lr_end_fraction must be in [0, 1], got {self.sft_lr_end_fraction}")
        if self.sft_warmup_steps < 0 or self.sft_eval_every < 1:
            raise ValueError("rl.sft_warmup_steps must be >= 0 and rl.sft_eval_every >= 1")
        for name in ("sft_checkpoint_every", "reward_model_checkpoint_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"rl.{name} must be >= 1 (steps between checkpoints), got {getattr(self, name)}")
        if self.imagined_return not in ("success", "score"):
            raise ValueError(f"rl.imagined_return must be success|score, got {self.imagined_return!r}")
        if self.reward_labels not in ("state", "tail"):
            raise ValueError(f"rl.reward_labels must be state|tail, got {self.reward_labels!r}")
        if self.positive_tail < 1:
            raise ValueError(f"rl.positive_tail must be >= 1, got {self.positive_tail}")
        if self.env_starts not in ("initial", "keyframes"):
            raise ValueError(f"rl.env_starts must be initial|keyframes, got {self.env_starts!r}")
        if self.eval_replay_episodes < 0:
            raise ValueError(f"rl.eval_replay_episodes must be >= 0 (0 = no replay), got {self.eval_replay_episodes}")
