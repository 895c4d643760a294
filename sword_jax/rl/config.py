"""RL section of the experiment config (owned by sword_jax.rl), one sub-section per concern.

``rl`` itself holds what every stage shares (the action chunk, the frames and proprio the policy and
detector see, the success threshold); the rest lives where it is used::

    rl.policy        the VLA policy's architecture                      (sword_jax.rl.policy)
    rl.sft           behaviour cloning, the policy GRPO starts from     (sword_jax.rl.sft, train.train_policy)
    rl.reward_model  the success detector                               (sword_jax.rl.reward_model, train.train_reward)
    rl.grpo          the GRPO update, its sampled rollouts, evaluations (sword_jax.rl.grpo, train.grpo)
    rl.imagined      rollouts in the learned simulator                  (sword_jax.rl.rollout, train.grpo)
    rl.env           acting in the ground-truth environments            (sword_jax.rl.env_rollout, policy_success)
    rl.value         the value that closes short GRPO rollouts          (sword_jax.rl.value)

On the command line: ``--rl.sft.steps=2000``, ``--rl.grpo.group_size=8``. The flat keys of earlier
versions (``--rl.sft_steps``) are refused naming the new key (:data:`RENAMED`).
"""

import dataclasses
from typing import ClassVar

DECODERS = ("full", "light")  # rl.imagined.decoder
IMAGINED_REWARDS = ("detector", "executed", "calibrated")  # rl.imagined.reward
START_ENCODINGS = ("window", "prefix")  # rl.imagined.start_encoding
CALIBRATIONS = ("false_success", "separation")  # rl.refresh.calibration


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    """The VLA policy's architecture (:class:`sword_jax.rl.policy.VLAPolicy`).

    Attributes:
      width: base width of the policy (image encoder channels, token width).
      layers: transformer layers of the instruction / fusion encoder.
      heads: attention heads of the policy transformer.
      max_instruction_bytes: byte-level instruction tokens (padded / truncated).
      proprio_encoding: 'rot6d' turns the simulator's 8-D proprio (xyz, axis-angle, fingers) into
        continuous features (the axis-angle becomes two rotation-matrix columns); 'raw' uses it as is.
    """

    width: int = 64
    layers: int = 2
    heads: int = 4
    max_instruction_bytes: int = 96
    proprio_encoding: str = "rot6d"  # rot6d | raw

    def validate(self) -> None:
        if self.width % self.heads:
            raise ValueError(f"rl.policy.heads={self.heads} must divide rl.policy.width={self.width}")
        if self.proprio_encoding not in ("rot6d", "raw"):
            raise ValueError(f"rl.policy.proprio_encoding must be rot6d|raw, got {self.proprio_encoding!r}")


@dataclasses.dataclass(frozen=True)
class SFTConfig:
    """Behaviour cloning (:mod:`sword_jax.rl.sft`, ``train.train_policy``): steps and the number of
    demonstrations set how good the starting policy is.

    Attributes:
      steps / batch_size / learning_rate: SFT steps, batch size and peak learning rate.
      episodes_per_task: demonstrations per instruction it trains on (0 = all available).
      lr_end_fraction: the SFT cosine schedule ends at this fraction of its peak.
      warmup_steps: linear warm-up of the SFT learning rate.
      eval_every: SFT steps between teacher-forced metrics on held-out demonstrations.
      checkpoint_every: steps between the train-state checkpoints an SFT run resumes from
        (``train.train_policy``; the last step is always saved).
      init: a trained policy (a ``train.train_policy`` checkpoint directory or ``.npz``) that the pipeline
        starts from instead of behaviour cloning one: its ``sft_policy`` stage copies it into the run and
        checks it loads into this config's policy; "" trains one. ``train.train_policy`` and
        ``benchmarks.bench_policy sft`` fine-tune it instead: its parameters (proprio normalisation included)
        with a fresh optimizer, for ``steps``.
      image_aug: jitter the training frames' brightness, contrast, saturation and hue, and shift them, as VLA
        fine-tuning does (:mod:`sword_jax.rl.image_aug`); off by default.
      decoded_fraction: decoder-aware SFT: the share of each training batch's samples (``round(fraction x
        batch_size)`` of them, drawn per step) whose frame is the VAE's video round trip of the same frame (its
        episode encoded and decoded as one video, :mod:`sword_jax.rl.decoded_frames`), the frames GRPO in the world
        model shows the policy; held-out metrics stay on real frames. 0 = off (real frames only); > 0 needs a
        trained VAE (``--vae`` of ``train.train_policy`` and ``benchmarks.bench_policy sft``).
      decoded_source: where the decoded frames come from: ``vae``, the VAE's round trip of the real frame;
        ``world_model``, the frame the world model imagines at that step when the episode's own actions are replayed
        from a real frame up to ``decoded_window`` actions before (:mod:`sword_jax.rl.imagined_frames`), labelled
        with the demonstration's action there. ``world_model`` also needs the world model (``--world-model``).
      decoded_window: with ``decoded_source=world_model``, the actions each replay runs from its real start frame;
        0 = an imagined rollout's, ``rl.imagined.max_chunks x`` the actions executed per decision.
    """

    steps: int = 200
    batch_size: int = 32
    learning_rate: float = 3e-4
    episodes_per_task: int = 0  # 0 = all available demonstrations
    lr_end_fraction: float = 0.1
    warmup_steps: int = 50
    eval_every: int = 100
    checkpoint_every: int = 100
    init: str = ""
    image_aug: bool = False
    decoded_fraction: float = 0.0  # 0 = real frames only
    decoded_source: str = "vae"  # vae | world_model
    decoded_window: int = 0  # 0 = rl.imagined.max_chunks x actions per decision

    def validate(self) -> None:
        fraction = self.decoded_fraction
        if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0.0 <= fraction <= 1.0:
            raise ValueError(f"rl.sft.decoded_fraction must be a number in [0, 1] (the share of each SFT batch's "
                             f"frames taken from the VAE's round trip; 0 = off), got {fraction!r}")
        if self.decoded_source not in ("vae", "world_model"):
            raise ValueError(f"rl.sft.decoded_source must be vae or world_model, got {self.decoded_source!r}")
        if isinstance(self.decoded_window, bool) or not isinstance(self.decoded_window, int) or self.decoded_window < 0:
            raise ValueError(f"rl.sft.decoded_window must be an integer >= 0 (actions a replay runs; 0 = an imagined "
                             f"rollout's), got {self.decoded_window!r}")
        if not isinstance(self.image_aug, bool):
            raise ValueError(f"rl.sft.image_aug must be true or false, got {self.image_aug!r}")
        if not isinstance(self.init, str):
            raise ValueError(f"rl.sft.init must be a path (or \"\" to train a policy), got {self.init!r}")
        if not 0.0 <= self.lr_end_fraction <= 1.0:
            raise ValueError(f"rl.sft.lr_end_fraction must be in [0, 1], got {self.lr_end_fraction}")
        if self.warmup_steps < 0 or self.eval_every < 1:
            raise ValueError("rl.sft.warmup_steps must be >= 0 and rl.sft.eval_every >= 1")
        if self.checkpoint_every < 1:
            raise ValueError(f"rl.sft.checkpoint_every must be >= 1 (steps between checkpoints), got "
                             f"{self.checkpoint_every}")


@dataclasses.dataclass(frozen=True)
class RewardModelConfig:
    """The success detector (:mod:`sword_jax.rl.reward_model`, ``train.train_reward``).

    Attributes:
      steps / batch_size / learning_rate: detector training.
      labels: what the success detector learns. ``state`` (default): the task's success
        predicate on the state each frame shows (the simulator's per-step success), over whole
        episodes, so frames after success (bowl resting on the plate, the arm retreating) are
        positives and frames with the bowl lifted off again negatives. ``tail``: the last
        ``positive_tail`` frames of successful episodes read up to their first success, i.e. the
        frames just *before* the bowl lands (the earlier recipe; see README for what it measured).
      positive_tail: the last this-many frames of a successful episode are positives (``labels=tail``).
      width: base channels of the success-detector CNN.
      image_size: frame size the detector reads (frames are resized to it); 0 = ``rl.image_size``, the
        policy's. The task's tolerances (the bowl within 3 cm of the plate's centre, 5 mm above it) span a
        pixel or two at 64 px; a larger size lets the detector see them (the learned simulator's frames are
        ``data.image_size``, the light decoder's ``light_decoder.frame_size``).
      checkpoint_every: steps between the train-state checkpoints a reward-model run resumes from
        (``train.train_reward``; the last step is always saved).
    """

    steps: int = 200
    batch_size: int = 32
    learning_rate: float = 1e-3
    labels: str = "state"  # state | tail
    positive_tail: int = 8
    width: int = 16
    image_size: int = 0
    checkpoint_every: int = 100

    def validate(self) -> None:
        if self.labels not in ("state", "tail"):
            raise ValueError(f"rl.reward_model.labels must be state|tail, got {self.labels!r}")
        if self.positive_tail < 1:
            raise ValueError(f"rl.reward_model.positive_tail must be >= 1, got {self.positive_tail}")
        if self.checkpoint_every < 1:
            raise ValueError(f"rl.reward_model.checkpoint_every must be >= 1 (steps between checkpoints), got "
                             f"{self.checkpoint_every}")
        if self.image_size and (self.image_size < 16 or self.image_size % 8):
            raise ValueError(f"rl.reward_model.image_size must be 0 (the policy's rl.image_size) or a multiple of 8 "
                             f">= 16, got {self.image_size}")


@dataclasses.dataclass(frozen=True)
class GRPOConfig:
    """The GRPO update, the rollouts it samples (in any simulator) and its evaluations
    (:mod:`sword_jax.rl.grpo`, :mod:`sword_jax.rl.grpo_loop`, ``train.grpo``).

    Attributes:
      steps: GRPO updates per run.
      rollout_batch: start states per GRPO step (each expanded to ``group_size`` trajectories).
      group_size: G, trajectories sampled per start state (GRPO group).
      learning_rate: GRPO learning rate.
      clip_low / clip_high: PPO ratio clip range ``[1 - clip_low, 1 + clip_high]`` (DAPO clip-higher).
      kl_coef: weight of the k3 KL estimate to the reference (SFT) policy; 0 = off.
      ppo_epochs: passes over each batch of rollouts (each ``minibatches`` gradient steps).
      minibatches: gradient steps per pass, each on an equal share of the batch's trajectories
        (shuffled per pass), its objective normalised within the share. With ``ppo_epochs = minibatches
        = 1`` the update is on-policy (the ratio is 1 and the clip never binds: REINFORCE with a group
        baseline); from the second step of a batch on the ratio moves and the clip is a trust region
        (SimpleVLA-RL and RLinf take about 4 steps per batch).
      max_sample_rounds: dynamic sampling (DAPO; SimpleVLA-RL, RLinf): a step samples ``rollout_batch``
        groups, and while fewer than ``rollout_batch`` of the groups sampled so far have mixed outcomes
        (some successes and some failures: the only ones with a learning signal) it samples another
        ``rollout_batch``, up to this many rounds; the update batch is ``rollout_batch`` groups, the mixed
        ones first, then (if the rounds ran out) groups without signal, which ``filter_groups`` masks.
        1 = one round, no resampling. Ground-truth GRPO on the MJX backend only.
      min_mixed_fraction: with ``max_sample_rounds > 1``, a step stops sampling once this fraction of
        ``rollout_batch`` groups are mixed (1.0 = all; on `small` at temperature 0.5 about 97% of groups are
        mixed, and a second round of 512 episodes to find the missing two doubled the step's time).
      min_mixed_groups: a step whose update batch holds fewer groups with mixed outcomes than this applies
        no update (parameters and optimizer state stay as they were; the step still counts). The objective
        is normalised over the mixed groups and Adam scales its step to the gradient, so one or two groups
        move the policy as far as a full batch, in a direction set by a few trajectories (DAPO and
        SimpleVLA-RL never train on an under-filled batch). 0 = off.
      loss_norm: 'trajectory' averages token losses within each trajectory (normalising by its
        length) and then over trajectories (GRPO); 'token' averages over all valid tokens (DAPO).
      filter_groups: drop groups whose rewards are all equal (no learning signal).
      success_bonus: added to a trajectory's return when it reaches success.
      scale_by_std: divide each group's centred returns by their std (GRPO, default); false leaves them centred
        (Dr. GRPO), so a group's advantages keep the size of its returns' spread. With a continuous return
        (``rl.value``) the std turns a group whose returns differ only by the estimate's noise into advantages
        as large as a group whose trajectories differ in success; Adam then moves the policy as far for either.
      shuffle_returns: a control, not a method: each group's returns are permuted among its trajectories before
        the advantages, with the update's key. The batch keeps its groups, their spreads and the gradient's noise,
        and loses its expected direction, so a run with it measures what the noise alone does to the policy.
      temperature: sampling temperature of the policy during rollouts.
      update_microbatch: trajectories per forward/backward pass of the GRPO update (0 = the whole
        batch at once); gradients are summed over the micro-batches, so the update is the same up to
        float summation order while activation memory falls by batch / micro-batch (the whole
        ``small`` batch, 64 trajectories x 55 decisions, asked for 47 GiB at once on an H100).
      eval_every: GRPO steps between ground-truth evaluations.
      eval_episodes_per_task: initial states per task in ground-truth evaluation (paper: 50).
      eval_sampled: every ground-truth evaluation also runs the sampled policy (at ``temperature``,
        the policy the update trains) on the same episodes, stored as ``sampled`` beside the greedy
        success: whether GRPO lifts the policy it samples but not its argmax (README, issue 17).
    """

    steps: int = 10
    rollout_batch: int = 4
    group_size: int = 8
    learning_rate: float = 1e-5
    clip_low: float = 0.2
    clip_high: float = 0.28
    kl_coef: float = 0.0
    ppo_epochs: int = 1
    minibatches: int = 1
    max_sample_rounds: int = 1
    min_mixed_fraction: float = 0.9
    min_mixed_groups: int = 0  # fewer mixed groups in the update batch: no update; 0 = off
    loss_norm: str = "trajectory"  # trajectory | token
    filter_groups: bool = True
    success_bonus: float = 1.0
    scale_by_std: bool = True
    shuffle_returns: bool = False
    temperature: float = 1.0
    update_microbatch: int = 0  # trajectories per forward/backward of the GRPO update; 0 = all
    eval_every: int = 5
    eval_episodes_per_task: int = 50
    eval_sampled: bool = False

    def validate(self) -> None:
        if self.steps < 0 or self.rollout_batch < 1 or self.eval_every < 1 or self.eval_episodes_per_task < 1:
            raise ValueError(f"rl.grpo.steps must be >= 0 and rollout_batch, eval_every, eval_episodes_per_task >= 1, "
                             f"got steps={self.steps}, rollout_batch={self.rollout_batch}, eval_every={self.eval_every}, "
                             f"eval_episodes_per_task={self.eval_episodes_per_task}")
        if not self.learning_rate > 0.0:
            raise ValueError(f"rl.grpo.learning_rate must be > 0, got {self.learning_rate}")
        if self.group_size < 2:
            raise ValueError(f"rl.grpo.group_size must be >= 2 for group-normalised advantages, got {self.group_size}")
        if not 0.0 <= self.clip_low < 1.0 or self.clip_high < 0.0:
            raise ValueError(f"rl.grpo.clip_low must be in [0, 1) and clip_high >= 0, got "
                             f"{self.clip_low}/{self.clip_high}")
        if self.kl_coef < 0.0:
            raise ValueError(f"rl.grpo.kl_coef must be >= 0, got {self.kl_coef}")
        if self.ppo_epochs < 1:
            raise ValueError(f"rl.grpo.ppo_epochs must be >= 1, got {self.ppo_epochs}")
        if self.minibatches < 1 or (self.rollout_batch * self.group_size) % self.minibatches:
            raise ValueError(f"rl.grpo.minibatches={self.minibatches} must be >= 1 and divide rl.grpo.rollout_batch x "
                             f"rl.grpo.group_size = {self.rollout_batch * self.group_size}")
        if not 0.0 < self.min_mixed_fraction <= 1.0:
            raise ValueError(f"rl.grpo.min_mixed_fraction must be in (0, 1], got {self.min_mixed_fraction}")
        groups = self.min_mixed_groups
        if isinstance(groups, bool) or not isinstance(groups, int) or groups < 0:
            raise ValueError(f"rl.grpo.min_mixed_groups must be an int >= 0 (0 = every batch updates), got {groups!r}")
        if self.max_sample_rounds < 1:
            raise ValueError(f"rl.grpo.max_sample_rounds must be >= 1 (1 = no resampling), got {self.max_sample_rounds}")
        if self.temperature <= 0.0:
            raise ValueError(f"rl.grpo.temperature must be > 0, got {self.temperature}")
        if not isinstance(self.scale_by_std, bool):
            raise ValueError(f"rl.grpo.scale_by_std must be true or false, got {self.scale_by_std!r}")
        if not isinstance(self.shuffle_returns, bool):
            raise ValueError(f"rl.grpo.shuffle_returns must be true or false, got {self.shuffle_returns!r}")
        if self.loss_norm not in ("trajectory", "token"):
            raise ValueError(f"rl.grpo.loss_norm must be trajectory|token, got {self.loss_norm!r}")
        if self.update_microbatch < 0:
            raise ValueError(f"rl.grpo.update_microbatch must be >= 0 (0 = the whole batch), got "
                             f"{self.update_microbatch}")
        share = self.rollout_batch * self.group_size // max(self.minibatches, 1)
        if self.update_microbatch and share % self.update_microbatch:
            raise ValueError(f"rl.grpo.update_microbatch={self.update_microbatch} must divide the trajectories of one "
                             f"minibatch, rl.grpo.rollout_batch x rl.grpo.group_size / rl.grpo.minibatches = {share}")


@dataclasses.dataclass(frozen=True)
class ImaginedConfig:
    """Rollouts in the learned simulator (:mod:`sword_jax.rl.rollout`, ``train.grpo --simulator
    world_model``) and the evaluations that only GRPO in it makes.

    Attributes:
      max_chunks: step limit of an imagined rollout, in action chunks (policy decisions).
      return_rule: the return of an imagined trajectory. ``success`` (default): ``1 +
        rl.grpo.success_bonus`` on success, else 0, the same return GRPO in the ground-truth
        environments uses (where the update was validated: +16.4 points on `small`), so a group whose
        trajectories all fail carries no signal and is filtered. ``score``: the summed per-chunk
        changes of the detector's score plus the bonus on success (the earlier rule): every
        group then has a spread, and failing groups are ranked by the detector's score on frames
        that are not successes, a signal GRPO can climb without succeeding.
      execute_steps: actions of each chunk executed inside the learned simulator before
        the policy re-plans: a multiple of 4 (the world model's latent frame) dividing ``rl.chunk_len``.
        None (default) = ``rl.chunk_len``, whole chunks (one world-model call per chunk); 4 = the world
        model still predicts the chunk's frames from all its actions, keeps the first latent's 4 frames
        and the policy re-plans from the last of them (twice the world-model calls per action).
        ``max_chunks`` counts policy decisions either way.
      proprio: what the policy reads as proprio inside the learned simulator, which predicts
        frames only. ``missing`` (default): the policy's learned "missing proprio" input, a mode SFT
        trains by proprio dropout. ``reckoned``: integrated from the start state's proprio and the
        executed actions by the controller's action convention (:mod:`sword_jax.rl.proprio_reckoning`).
        Measured on `small` in the real environments (README), the SFT policy succeeds 0.265 with true
        proprio, 0.200 with it missing and 0.160 with it reckoned (200 episodes each): the reckoning's
        drift (2.4 cm after 8 actions, 5.4 cm after 32) misleads the policy more than no proprio does.
        Either way the imagined mode is not the true-proprio mode, hence ``eval_masked_proprio``.
      keyframe_fraction: imagined rollouts (and ground-truth ones with ``rl.env.starts=keyframes``)
        start at latent-aligned keyframes drawn from the first ``keyframe_fraction`` of each
        demonstration (from ``keyframe_from`` on; :func:`sword_jax.rl.data.keyframe_starts`; WoVR's keyframes).
        0.5 (default): the first half, so many rollouts start with the task under way. 0: always the first
        keyframe (frame ``4 k``, the arm barely moved), as the real evaluations start; raise ``max_chunks`` to
        cover a whole episode then (``small``'s 220 steps: 28 chunks of 8).
      keyframe_from: the keyframes' lower bound: they are drawn from the part of each demonstration between
        fractions ``keyframe_from`` and ``keyframe_fraction`` of it (0 <= ``keyframe_from`` <= ``keyframe_fraction``;
        equal: the one keyframe there). 0 (default): from the first keyframe. For starting GRPO only in the phases
        of the task where the learned simulator's closed loop keeps reality's payment. On `small`, by start step
        (``benchmarks.bench_grpo_reward_source``'s ``by_start``), reality pays the policy's rollouts 5-7% when it
        acts on the world model's frames against 39-44% on real frames for starts in the first 24 actions, 46-48%
        against 75-80% for starts at 24-47 actions and 89-96% against 80-83% for starts at 48 or later.
      eval_masked_proprio: every real-environment evaluation of GRPO in the learned simulator also
        runs the policy with proprio masked (its "missing proprio" input mode; one more evaluation
        each), stored as ``proprio_masked`` in the success curve: with ``proprio=missing``
        that is the mode GRPO trained, so it measures the update free of the input-mode shift, and
        the true-proprio curve beside it measures how much of it carries over. On by default.
      eval_replay_episodes: at every real-environment evaluation of GRPO in the learned simulator,
        this many of the evaluated episodes (spread over the tasks) are replayed in the learned
        simulator: their executed actions, open loop, from the same start (frame 4 k, the real
        history before it), scored by the success detector (:mod:`sword_jax.rl.sim_agreement`).
        Stored as ``replay`` in the success curve: how often the simulator calls a real failure a
        success (``false_success``, what GRPO can exploit) or misses a real success. 0 = off.
      eval_replay_settle_steps: hold actions (zero pose deltas, last gripper command) replayed and
        scored after each episode's last action. A real episode that succeeded ended at the action
        that reached success, so without them the imagined scene has no frame after it: on `small`
        (2026-11-26) the replay missed 89% of the real successes that took under 60 actions, while
        imagined successes were common later in other episodes. Every episode gets the same window.
      success_frames: an imagined trajectory succeeds once this many consecutive predicted frames
        score at or above ``rl.success_threshold`` (counted across chunks; 1 = any frame, the rule so
        far). The replay's ``sustained_success_sweep`` measures what k = 1/2/4/8 would do to false
        and missed successes before a run uses it.
      shared_group_noise: the learned simulator's sampling noise is drawn once per GRPO group and shared by
        its members (:func:`sword_jax.rl.rollout.simulator_keys`), so within a group only the actions
        differ; off (default): every trajectory draws its own (on `small` a second noise draw changed
        19-31% of replayed real episodes' verdicts, and a lone noise-made success in a group takes a large
        advantage).
      confirm_success: an imagined success counts only when a second, independent imagination of the
        trajectory's executed actions (other simulator noise, same start) succeeds too
        (:func:`sword_jax.rl.sim_agreement.confirm_successes`; its effect on real episodes is the replay's
        ``confirmed_by_second_replay``); doubles the simulator's work per step. Off by default.
      oversample: dynamic sampling inside the learned simulator's jitted step (static shapes): a GRPO step
        rolls out ``oversample x rl.grpo.rollout_batch`` start states (each a group of ``group_size``
        trajectories; :attr:`RLConfig.imagined_starts_per_step`) and updates on ``rollout_batch`` of the
        groups, those with mixed outcomes first (a random choice among them), then, if fewer are mixed, groups
        without signal (which ``rl.grpo.filter_groups`` masks) (:func:`sword_jax.rl.grpo.select_groups`). The
        rollout costs ``oversample`` times as much; the update's shape is unchanged. Measured on GPUs, only
        31-45% of a step's 32 imagined groups were mixed (95-98% of 64 in ground-truth GRPO), so the update
        averaged over ~10 signal groups. 1 (default) = no oversampling, the step as it was.
      guard_margin: the exploitation guard (:mod:`sword_jax.rl.sim_guard`): at each evaluation that replays
        real episodes in the learned simulator, a false-success rate above step 0's by more than this rolls
        the policy back to the last evaluation that passed; 0 (default) = off.
      guard_min_failures: real failures a replay must hold before the guard judges it.
      guard_on: what the exploitation guard reads: ``replay`` (the evaluation's replay of real episodes in the
        simulator) or ``verify`` (the refresh's check of the policy's own imagined groups executed for real,
        ``rl.refresh.verify_starts``: the real failures GRPO was paid for, the exploitation itself).
      reward: what pays an imagined trajectory. ``detector`` (default): the success detector on the simulator's
        frames, the learned simulator's own reward. ``executed``: the real environment (MJX), given the same
        actions open loop from the recorded state the imagined rollout started at (its keyframe); the imagined
        rollout then runs the whole horizon (the detector stops nothing) and its decisions after the real
        success are masked. The policy still acts on the simulator's frames, so this arm separates what the
        learned simulator's frames do to GRPO from what its reward does (:mod:`sword_jax.rl.imagined_check`);
        each step also logs the detector's verdict on the same trajectories against the real outcome. Needs
        ``rl.env.backend=mjx``, keyframes with recorded states and no ``confirm_success``; with a refresh
        (``rl.refresh.every``) only one that does not branch (``rl.refresh.branch=false``: the rollouts keep the
        keyframes' starts), which measures whether the refreshes make the simulator keep more of what reality
        pays the policy's actions.
        ``calibrated``: the first ``calibrate_steps`` steps are paid as ``executed``; from then on the detector
        pays, at the threshold those steps set on the policy's own closed loop: just above the median of their
        ``detector_threshold_bounded``, the score that leaves at most ``rl.refresh.max_false_success`` of their
        real failures paid (:func:`~sword_jax.rl.grpo.make_calibrated_step`; WMPO tunes its reward's threshold,
        here it is set by the real outcome of the policy's imagined actions). Needs what ``executed`` needs; its
        real rollouts are the calibration steps' ``rollout_batch x group_size`` each, and no refresh.
      calibrate_steps: with ``reward=calibrated``, the steps paid by execution before the detector pays.
      fidelity_trajectories: with ``reward=executed``, the first this-many trajectories of each step also keep
        the real frame at the end of every decision of their execution, and the step logs where the closed loop
        through the simulator leaves the real one (:func:`~sword_jax.rl.imagined_check.closed_loop_fidelity`):
        at each decision ``k`` the frame the policy read against the real frame the same actions reached
        (``closed_loop_frame_error_k``) and the policy's greedy actions on the two (``closed_loop_action_gap_k``,
        action units), and to place the error, the simulator's frame against the real one a decision earlier
        (``closed_loop_frame_error_prev_k``, ``closed_loop_action_gap_prev_k``) and the real motion over the
        decision (``closed_loop_motion_k``), and the frame's finest detail over the real one's
        (``closed_loop_sharpness_k``, below 1 for a blur). With the world model decoding through its VAE, also the
        VAE's round trip of the real frame against the real frame (``closed_loop_frame_error_vae_k``,
        ``closed_loop_action_gap_vae_k``, ``closed_loop_sharpness_vae_k``): the floor a world model with faithful
        dynamics would still show through that VAE (each of these real frames is encoded and decoded once more, as
        a still video).
        0 = off.
      sim_microbatches: the learned simulator's init and step run over the trajectories in this
        many slices, one after another (each slice vmapped), so their activations -- the VAE
        decoder's full-resolution features above all -- are held for ``1/sim_microbatches`` of them
        at a time. 1 = all at once. The trajectory count must divide evenly; each slice takes
        every ``sim_microbatches``-th trajectory, so a data-sharded batch stays spread over devices.
        0 (default): the fewest slices of at most the simulator's ``max_slice`` trajectories
        (:func:`sword_jax.rl.rollout.microbatches_for`; one slice for `small`, 4 for the 5B model's 32).
      sim_precision: how the world-model simulator runs (:mod:`sword_jax.rl.sim_builder`): ``fast``
        (default: the VAE decodes in bfloat16 with sub-pixel upsampling, weights stored in the compute
        dtype) or ``float32`` (the exact float32 decode at the highest precision, weights as loaded).
      decoder: what turns the world model's latents into the frames GRPO's policy and success detector read.
        ``full`` (default): the VAE's decoder at ``data.image_size``. ``light``: the light decoder
        (:mod:`sword_jax.vae.light_decoder`) distilled from it by the pipeline's ``light_decoder`` stage, at
        ``light_decoder.frame_size`` (default ``rl.image_size``), a small fraction of the work per frame. The
        replay of real episodes then runs through it too (it measures the simulator GRPO trains in);
        evaluations, videos and metrics of the world model keep the full decoder.
      start_encoding: how a keyframe's start latents (the first frame's and the context's) are made. ``window``
        (default): the VAE encodes the first frame and the ``4 (k + 1)`` frames up to the keyframe, the oldest
        four only warming its causal cache (:func:`~sword_jax.rl.world_model_sim.encode_history`; before frame 0
        the window repeats it). ``prefix``: it encodes the episode from its first frame to the keyframe
        (:func:`~sword_jax.rl.world_model_sim.encode_prefix`), as the latents stage encodes whole episodes, so the
        context is exactly the latent the world model was trained on; the longer video costs more encoding. It sets
        every start encoded from real frames, so a run never mixes the two: GRPO's steps (and ``bench_closed_loop``'s),
        the replays of real episodes (``eval_replay_episodes``, :mod:`~sword_jax.rl.sim_agreement`), the world
        model's replays for decoder-aware SFT (:mod:`~sword_jax.rl.imagined_frames`), and the refresh's branch and
        verify starts, replays and closed-loop segments (:mod:`~sword_jax.rl.refresh`; their real latents too).
    """

    max_chunks: int = 8
    return_rule: str = "success"  # success | score
    execute_steps: int | None = None  # None = rl.chunk_len (whole chunks)
    proprio: str = "missing"  # missing | reckoned
    keyframe_fraction: float = 0.5  # keyframes from the first this-fraction of each demonstration
    keyframe_from: float = 0.0  # ... and from the fraction of it this far in onwards
    eval_masked_proprio: bool = True  # also evaluate GRPO-in-the-world-model policies with proprio masked
    eval_replay_episodes: int = 100  # real evaluation episodes replayed in the learned simulator; 0 = off
    eval_replay_settle_steps: int = 8  # hold actions scored after each replayed episode's last action
    success_frames: int = 1  # consecutive detector frames >= the threshold an imagined success needs
    sim_microbatches: int = 0  # simulator step over trajectories in this many sequential slices; 0 = auto
    sim_precision: str = "fast"  # fast | float32
    decoder: str = "full"  # full | light
    shared_group_noise: bool = False  # one simulator noise draw per GRPO group
    confirm_success: bool = False  # a success counts only if a second imagination of its actions succeeds
    oversample: int = 1  # roll out this many times rollout_batch groups, update on rollout_batch (mixed first)
    guard_margin: float = 0.0  # roll back when replay false success exceeds step 0's by this; 0 = off
    guard_min_failures: int = 20  # real failures a replay needs before the guard judges it
    guard_on: str = "replay"  # replay | verify: the false-success rate the exploitation guard judges
    reward: str = "detector"  # detector | executed: what pays an imagined trajectory (see above)
    fidelity_trajectories: int = 64  # with reward=executed: trajectories whose closed loop is compared; 0 = off
    calibrate_steps: int = 0  # with reward=calibrated: steps paid by execution that set the detector's threshold
    start_encoding: str = "window"  # window | prefix: how a keyframe's context latents are encoded (see above)

    @property
    def executes(self) -> bool:
        """Whether some step's trajectories are paid by executing their actions (``executed``, ``calibrated``)."""
        return self.reward in ("executed", "calibrated")

    def validate(self) -> None:
        if self.max_chunks < 1:
            raise ValueError(f"rl.imagined.max_chunks must be >= 1, got {self.max_chunks}")
        if self.sim_microbatches < 0:
            raise ValueError(f"rl.imagined.sim_microbatches must be >= 1 (0 = auto), got {self.sim_microbatches}")
        if self.sim_precision not in ("fast", "float32"):
            raise ValueError(f"rl.imagined.sim_precision must be fast|float32, got {self.sim_precision!r}")
        if self.decoder not in DECODERS:
            raise ValueError(f"rl.imagined.decoder must be {'|'.join(DECODERS)}, got {self.decoder!r}")
        if not 0.0 <= self.guard_margin < 1.0 or self.guard_min_failures < 1:
            raise ValueError(f"rl.imagined.guard_margin must be in [0, 1) (0 = off) and guard_min_failures >= 1, got "
                             f"{self.guard_margin}, {self.guard_min_failures}")
        if self.guard_on not in ("replay", "verify"):
            raise ValueError(f"rl.imagined.guard_on must be replay|verify, got {self.guard_on!r}")
        if self.fidelity_trajectories < 0:
            raise ValueError(f"rl.imagined.fidelity_trajectories must be >= 0 (0 = off), got {self.fidelity_trajectories}")
        if self.reward not in IMAGINED_REWARDS:
            raise ValueError(f"rl.imagined.reward must be {'|'.join(IMAGINED_REWARDS)}, got {self.reward!r}")
        if (self.reward == "calibrated") != (self.calibrate_steps > 0) or self.calibrate_steps < 0:
            raise ValueError("rl.imagined.calibrate_steps (the steps paid by execution that set the detector's "
                             "threshold) must be >= 1 with rl.imagined.reward=calibrated and 0 otherwise, got "
                             f"{self.calibrate_steps} with reward={self.reward!r}")
        if not 0.0 <= self.keyframe_fraction <= 1.0:
            raise ValueError(f"rl.imagined.keyframe_fraction must be in [0, 1], got {self.keyframe_fraction}")
        if not 0.0 <= self.keyframe_from <= self.keyframe_fraction:
            raise ValueError(f"rl.imagined.keyframe_from must be in [0, rl.imagined.keyframe_fraction] (the keyframes' "
                             f"window of each demonstration), got keyframe_from={self.keyframe_from} with "
                             f"keyframe_fraction={self.keyframe_fraction}")
        if self.start_encoding not in START_ENCODINGS:
            raise ValueError(f"rl.imagined.start_encoding must be {'|'.join(START_ENCODINGS)}, got "
                             f"{self.start_encoding!r}")
        if self.return_rule not in ("success", "score"):
            raise ValueError(f"rl.imagined.return_rule must be success|score, got {self.return_rule!r}")
        if self.proprio not in ("reckoned", "missing"):
            raise ValueError(f"rl.imagined.proprio must be reckoned|missing, got {self.proprio!r}")
        if self.eval_replay_episodes < 0:
            raise ValueError(f"rl.imagined.eval_replay_episodes must be >= 0 (0 = no replay), got "
                             f"{self.eval_replay_episodes}")
        if self.success_frames < 1:
            raise ValueError(f"rl.imagined.success_frames must be >= 1 (1 = any frame), got {self.success_frames}")
        if self.eval_replay_settle_steps < 0:
            raise ValueError(f"rl.imagined.eval_replay_settle_steps must be >= 0, got {self.eval_replay_settle_steps}")
        if self.oversample < 1:
            raise ValueError(f"rl.imagined.oversample must be >= 1 (start states rolled out per GRPO step, in units of "
                             f"rl.grpo.rollout_batch; 1 = no oversampling), got {self.oversample}")


@dataclasses.dataclass(frozen=True)
class RefreshConfig:
    """Keeping the learned simulator honest while GRPO moves the policy (:mod:`sword_jax.rl.refresh`).

    Every ``every`` GRPO steps (and at step 0) ``episodes`` real episodes of the current policy are
    collected in the ground-truth environments (MJX), the world model is fine-tuned on them (its DLB
    cache refreshed) and the success detector on their real frames and on the world model's replays of
    them labelled with the real outcome; its threshold is set on held-out replays so that at most
    ``max_false_success`` of the real failures are imagined successes. With ``branch`` the next imagined
    rollouts start from the new real episodes' states, every phase of them (MBPO's branched rollouts).

    Attributes:
      every: GRPO steps between refreshes, a multiple of ``rl.grpo.eval_every``; 0 = never (off).
      episodes: real episodes collected per refresh.
      budget: real episodes the whole run may collect (evaluation episodes not counted); a refresh takes
        what is left of it, none once it is spent (the models are then kept as they are).
      episode_steps: actions of each collected episode (the policy keeps acting after a success); 0 =
        ``sim.max_steps``. At least ``data.episode_frames`` (the world model's training windows).
      world_model_steps / world_model_learning_rate: the fine-tune of the world model per refresh, on the
        run's training latents plus as many of the policy's episodes, drawn from every refresh so far (half
        of its segments show what the moving policy really did).
      detector_steps: the fine-tune of the detector per refresh.
      replay_share: share of each detector batch taken from the world model's replays of real episodes
        (the rest from the real frames, labelled by the task's success predicate).
      calibrate_fraction: share of a refresh's episodes whose replays set the threshold (and are not
        trained on); the others' replays train the detector.
      max_false_success: the bound on imagined success among real failures that sets the threshold.
      calibration: how the threshold is set on the held-out replays: ``false_success`` (the lowest threshold
        within ``max_false_success``) or ``separation`` (the one that separates real successes from real
        failures best: GRPO's learning signal, :func:`~sword_jax.rl.sim_agreement.calibrate_separation`).
      calibrate_over: what of each held-out replay the threshold is set over: ``rollout`` (its first
        actions, as many as GRPO's imagined rollouts run: the run's horizon, each of ``horizons`` at the
        first refresh, else ``rl.imagined.max_chunks x execute_steps``) or ``episode`` (the whole replay).
      branch: imagined rollouts start at the latest refresh's real states (else at the demonstrations'
        keyframes).
      horizons: candidate lengths of the imagined rollouts, in actions (multiples of the imagined execution,
        ``rl.imagined.execute_steps``); empty: ``rl.imagined.max_chunks`` as configured. Else the first
        refresh replays held-out real episodes in the refreshed simulator and the run takes the longest
        candidate by which the calibrated detector still separates real successes from real failures by
        ``min_separation`` (imagined success among real successes minus among real failures), or the
        best-separating one when none does (MBPO: branch short where the model is trusted; a horizon too
        short for any success pays no reward). Every later refresh measures the separation at that horizon
        again (its record's ``trust``).
      min_separation: see ``horizons``.
      pause_untrusted: GRPO steps after a refresh whose ``trust`` falls below ``min_separation`` leave the
        policy unchanged (their imagined rollouts still run and are logged, ``paused`` = 1): the policy is
        not moved by a reward measured not to follow real outcomes. Needs ``horizons``.
      real_guard_margin: the real-success guard (:class:`~sword_jax.rl.sim_guard.RealSuccessGuard`): a refresh
        whose real episodes succeed less often than step 0's refresh's by more than this rolls the policy back
        to the last evaluation that passed; 0 (default) = off. The difference of two shares of 64 episodes
        each has a standard error of about 0.09, so a margin below ~0.15 trips on noise now and then.
      real_guard_min_episodes: real episodes a refresh must hold before the real-success guard judges it.
      group_size: real episodes collected per start state (``episodes / group_size`` starts, each rolled
        out ``group_size`` times with the policy's sampling, as a GRPO group). 1 (default): one per start.
        Above 1 the world model is fine-tuned on different actions from the same state, and each refresh's
        replay reports ``within_group``: whether the simulator GRPO trained in ranks the real successes of
        a group above its real failures (:func:`~sword_jax.rl.sim_agreement.within_group_separation`: by the
        calibrated verdict, and by the detector's scores, threshold-free), the signal GRPO's group advantages
        need. Separation across episodes can be high while that is zero,
        when the verdict follows the start state rather than the actions. A refreshed run of
        ``rl.grpo.steps=0`` is the probe: step 0's refresh measures it for the simulator as trained.
      verify_starts: before each refresh, this many start states of the real environment (drawn as the refresh's
        are), each rolled out ``rl.grpo.group_size`` times by the current policy in the simulator GRPO trained in
        (its horizon, from rest: the first frame held still as history), and each imagined trajectory's actions
        executed open loop in the real environment from the same start (:mod:`~sword_jax.rl.imagined_check`).
        The record's ``verify`` says how many imagined successes are real (``precision``), how many real failures
        were paid (``false_success``) and the separation inside the groups: the truth of the rewards GRPO reads,
        which the replay of real episodes does not give. The executions count as real episodes against
        ``budget``; a refresh skips the check when the budget cannot pay for it. 0 (default) = off.
      closed_loop_starts: the world model's fine-tune also learns from its own closed loop
        (:mod:`~sword_jax.rl.closed_loop`): this many keyframe starts of the demonstrations (drawn as GRPO's are,
        for steps GRPO never reaches; a multiple of ``rl.imagined_starts_per_step``), each rolled out
        ``rl.grpo.group_size`` times by the current policy in the simulator GRPO trained in, over the run's
        horizon; each trajectory's actions executed from the keyframe's recorded state, and one segment per
        decision made of the simulator's own context and the real latents the actions reached. The executions count
        as real episodes against ``budget``; a refresh skips this part when the budget cannot pay for it. Needs
        keyframes with recorded states. 0 (default) = off.
      closed_loop_share: share of each fine-tune batch's rows taken from those segments (in (0, 1)).
    """

    every: int = 0
    episodes: int = 64
    budget: int = 0
    episode_steps: int = 0
    world_model_steps: int = 200
    world_model_learning_rate: float = 3e-5
    detector_steps: int = 200
    replay_share: float = 0.5
    calibrate_fraction: float = 0.5
    max_false_success: float = 0.05
    calibration: str = "false_success"  # false_success | separation
    calibrate_over: str = "rollout"  # rollout | episode
    branch: bool = True
    horizons: tuple[int, ...] = ()
    min_separation: float = 0.2
    pause_untrusted: bool = False
    real_guard_margin: float = 0.0  # roll back when a refresh's real success falls below step 0's by this; 0 = off
    real_guard_min_episodes: int = 32  # real episodes a refresh needs before the real-success guard judges it
    group_size: int = 1  # real episodes per start state (a GRPO group of real rollouts); 1 = one each
    verify_starts: int = 0  # start states whose imagined groups are executed in the real environment; 0 = off
    closed_loop_starts: int = 0  # keyframe starts whose closed loop (imagined vs executed) trains the world model
    closed_loop_share: float = 0.5  # share of the fine-tune's batch rows from the closed-loop segments

    def validate(self) -> None:
        if self.every < 0:
            raise ValueError(f"rl.refresh.every must be >= 0 (0 = off), got {self.every}")
        if not 0.0 <= self.real_guard_margin < 1.0 or self.real_guard_min_episodes < 1:
            raise ValueError(f"rl.refresh.real_guard_margin must be in [0, 1) (0 = off) and real_guard_min_episodes "
                             f">= 1, got {self.real_guard_margin}, {self.real_guard_min_episodes}")
        if self.real_guard_margin and not self.every:
            raise ValueError("rl.refresh.real_guard_margin needs rl.refresh.every > 0 (it judges the refreshes' real "
                             "episodes)")
        if self.group_size < 1:
            raise ValueError(f"rl.refresh.group_size must be >= 1 (real episodes per start state), got {self.group_size}")
        if self.verify_starts < 0:
            raise ValueError(f"rl.refresh.verify_starts must be >= 0 (0 = off), got {self.verify_starts}")
        if self.closed_loop_starts < 0 or not 0.0 < self.closed_loop_share < 1.0:
            raise ValueError(f"rl.refresh.closed_loop_starts must be >= 0 (0 = off) and closed_loop_share in (0, 1), "
                             f"got {self.closed_loop_starts}, {self.closed_loop_share}")
        if not self.every:
            return
        if self.episodes % self.group_size or self.budget % self.group_size:
            raise ValueError(f"rl.refresh.episodes={self.episodes} and budget={self.budget} must be multiples of "
                             f"rl.refresh.group_size={self.group_size} (whole groups of real episodes)")
        if self.real_guard_margin and self.real_guard_min_episodes > self.episodes:
            raise ValueError(f"rl.refresh.real_guard_min_episodes={self.real_guard_min_episodes} exceeds "
                             f"rl.refresh.episodes={self.episodes}: the real-success guard would judge no refresh")
        if self.episodes < 2 or self.budget < self.episodes:
            raise ValueError(f"rl.refresh: episodes must be >= 2 and budget >= episodes (the real episodes a run may "
                             f"use), got episodes={self.episodes}, budget={self.budget}")
        if self.episode_steps < 0 or self.world_model_steps < 1 or self.detector_steps < 1:
            raise ValueError(f"rl.refresh: episode_steps must be >= 0, world_model_steps and detector_steps >= 1, got "
                             f"{self.episode_steps}, {self.world_model_steps}, {self.detector_steps}")
        if self.world_model_learning_rate <= 0:
            raise ValueError(f"rl.refresh.world_model_learning_rate must be > 0, got {self.world_model_learning_rate}")
        if not 0.0 <= self.replay_share <= 1.0 or not 0.0 < self.calibrate_fraction < 1.0:
            raise ValueError(f"rl.refresh: replay_share must be in [0, 1] and calibrate_fraction in (0, 1), got "
                             f"{self.replay_share}, {self.calibrate_fraction}")
        if not 0.0 <= self.max_false_success < 1.0:
            raise ValueError(f"rl.refresh.max_false_success must be in [0, 1), got {self.max_false_success}")
        if self.calibration not in CALIBRATIONS or self.calibrate_over not in ("rollout", "episode"):
            raise ValueError(f"rl.refresh.calibration must be {'|'.join(CALIBRATIONS)} and calibrate_over "
                             f"rollout|episode, got {self.calibration!r}, {self.calibrate_over!r}")
        if any(h < 1 for h in self.horizons) or list(self.horizons) != sorted(set(self.horizons)):
            raise ValueError(f"rl.refresh.horizons must be increasing action counts >= 1, got {self.horizons}")
        if not -1.0 <= self.min_separation <= 1.0:
            raise ValueError(f"rl.refresh.min_separation must be in [-1, 1], got {self.min_separation}")
        if self.pause_untrusted and not self.horizons:
            raise ValueError("rl.refresh.pause_untrusted needs rl.refresh.horizons (the trust is the separation of "
                             "real outcomes at the run's horizon)")


@dataclasses.dataclass(frozen=True)
class ValueConfig:
    """A success-probability estimate that closes short GRPO rollouts (:mod:`sword_jax.rl.value`).

    Rollouts short enough for a learned simulator to stay honest rarely reach success, and a success-only return
    gives most of their groups no learning signal (model-based RL with short branched rollouts, MBPO, closes its
    horizon with a learned value). With ``episodes > 0`` a value network is fitted before the first GRPO step to
    ``episodes`` real episodes of the starting policy (from training-split states at rest, sampled at
    ``rl.grpo.temperature``, acting as GRPO's rollouts do, each run to the episode limit): it reads a frame and the
    instruction and predicts whether the episode that frame belongs to goes on to succeed. A training rollout that
    reaches its horizon without success or failure is then paid ``(1 + rl.grpo.success_bonus) x`` the value of its
    final frame instead of 0; a success is still paid ``1 + success_bonus``. Evaluations are unchanged.
    Ground-truth GRPO on MJX (``rl.env.backend=mjx``).

    Attributes:
      episodes: real episodes the value is fitted to (they count as real episodes the run used); 0 = off.
      steps / batch_size / learning_rate: the fit (AdamW, binary cross-entropy on frames drawn uniformly from
        the episodes' decisions, so its outputs stay calibrated probabilities).
      width: base channels of the value network's CNN.
      holdout: share of the episodes kept out of the fit, on which its calibration is reported.
      bootstrap: pay the rollouts cut at their horizon the value (default); false fits and reports it but pays
        success alone, the control of a run branched from the same episodes (``rl.env.starts=branch``).
      branch_starts: how ``rl.env.starts=branch`` draws its starts from the episodes' decisions: ``uniform``
        (default), or ``open``, in proportion to ``p (1 - p)`` of the fitted value's success probability there,
        where the outcome is still open (:func:`sword_jax.rl.jax_env_grpo.branch_starts`). Uniform draws put most
        starts in failing episodes, which run to the action limit and hold most decisions.
    """

    episodes: int = 0  # 0 = off
    steps: int = 1000
    batch_size: int = 128
    learning_rate: float = 1e-3
    width: int = 16
    holdout: float = 0.2
    bootstrap: bool = True
    branch_starts: str = "uniform"  # uniform | open

    def validate(self) -> None:
        if not isinstance(self.bootstrap, bool):
            raise ValueError(f"rl.value.bootstrap must be true or false, got {self.bootstrap!r}")
        if self.branch_starts not in ("uniform", "open"):
            raise ValueError(f"rl.value.branch_starts must be uniform|open, got {self.branch_starts!r}")
        for name in ("episodes", "steps", "batch_size", "width"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < (0 if name == "episodes" else 1):
                raise ValueError(f"rl.value.{name} must be an integer >= {0 if name == 'episodes' else 1}"
                                 f"{' (0 = off)' if name == 'episodes' else ''}, got {value!r}")
        if not self.learning_rate > 0.0:
            raise ValueError(f"rl.value.learning_rate must be > 0, got {self.learning_rate}")
        if not 0.0 <= self.holdout < 1.0:
            raise ValueError(f"rl.value.holdout must be in [0, 1), got {self.holdout}")


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """Acting in the ground-truth (MuJoCo) environments: every evaluation, the policy's own rollouts
    (``sim.policy_rollouts``) and GRPO there (``train.grpo --simulator env``; :mod:`sword_jax.rl.env_rollout`).

    Attributes:
      backend: the engine of ground-truth GRPO rollouts and of their evaluations. ``cpu`` (default):
        MuJoCo's C engine in worker processes (:mod:`sim.lockstep`), the policy batched on the device.
        ``mjx``: MJX on the accelerator, every episode of a GRPO step (or an evaluation) one ``lax.scan``
        with the JAX renderer (:mod:`sword_jax.rl.scan_rollout`, :mod:`sim.mjx_batch`): the same frames,
        proprio, action clipping and success as the C engine. On a CPU MJX is unusably slow.
      execute_steps: actions of each predicted chunk executed before the policy re-plans
        (``rl.chunk_len`` = open-loop chunks; 1 = re-plan every step).
      action_ensemble: ACT-style temporal ensembling when re-planning every step: each step of a
        greedy (evaluation) rollout executes the exponentially weighted mean of every chunk's
        prediction for it; sampled GRPO rollouts in the real environments re-plan every step.
        Measured on `small` (README): ensembling 0.715, every step 0.690, every 2 actions 0.490,
        every 4 0.350, open-loop 8 0.192.
      ensemble_decay: weight ``exp(-decay * age)`` of a prediction made ``age`` steps ago.
      proprio: what the policy reads as proprio in GRPO rollouts in the ground-truth environments
        (``train.grpo --simulator env``): ``true`` (default), the environment's; ``reckoned``, dead-reckoned
        from the executed actions as the learned simulator does (``rl.imagined.proprio=reckoned``);
        ``missing``, the "missing proprio" input (``rl.imagined.proprio=missing``). The environment and
        reward stay true, so a GRPO run in it isolates the input mode from world-model error; every
        evaluation then also measures that mode beside the true-proprio success.
      starts: where GRPO rollouts in the ground-truth environments start. ``initial`` (default):
        training-split initial states at rest, for ``sim.max_steps``. ``keyframes``: the
        demonstrations' recorded states at the keyframes GRPO in the learned simulator starts from
        (``rl.imagined.keyframe_from`` to ``keyframe_fraction`` of each, latent-aligned:
        :func:`sword_jax.rl.data.keyframe_starts`), for the
        learned simulator's horizon (``rl.imagined.max_chunks`` decisions of ``rl.imagined.execute_steps
        or rl.chunk_len`` actions, executed as it executes them; evaluations keep ``execute_steps``). With
        ``proprio=missing``, GRPO in the real environments then has the learned simulator's
        setting with true dynamics and true success: whether that setting can lift success from
        rest, free of world-model error. Both backends run every start and the proprio modes ``true``
        and ``missing``; ``reckoned`` runs on ``cpu`` only. ``branch`` (MJX only, with ``rl.value.episodes``):
        the states of the starting policy's own real episodes collected for the value, at every decision
        before their outcome, uniformly (MBPO's branched rollouts; :func:`sword_jax.rl.jax_env_grpo.branch_starts`),
        for the learned simulator's horizon and execution as ``keyframes`` runs them. ``rest``: training-split
        initial states at rest, as ``initial``, for that same horizon and execution: whole-episode GRPO's starts
        with a short rollout's cut, which tells the starts' share of a short rollout's effect from the cut's.
    """

    backend: str = "cpu"  # cpu | mjx
    execute_steps: int = 1
    action_ensemble: bool = True
    ensemble_decay: float = 0.1
    proprio: str = "true"  # true | reckoned | missing: the policy's proprio in ground-truth GRPO rollouts
    starts: str = "initial"  # initial | keyframes | branch | rest: where ground-truth GRPO rollouts start

    def validate(self) -> None:
        if self.action_ensemble and self.execute_steps != 1:
            raise ValueError(f"rl.env.action_ensemble needs rl.env.execute_steps=1 (a new chunk every step), got "
                             f"execute_steps={self.execute_steps}: set rl.env.action_ensemble=false to execute "
                             f"{self.execute_steps} actions per chunk")
        if self.ensemble_decay < 0.0:
            raise ValueError(f"rl.env.ensemble_decay must be >= 0, got {self.ensemble_decay}")
        if self.proprio not in ("true", "reckoned", "missing"):
            raise ValueError(f"rl.env.proprio must be true|reckoned|missing, got {self.proprio!r}")
        if self.starts not in ("initial", "keyframes", "branch", "rest"):
            raise ValueError(f"rl.env.starts must be initial|keyframes|branch|rest, got {self.starts!r}")
        if self.backend not in ("cpu", "mjx"):
            raise ValueError(f"rl.env.backend must be cpu|mjx, got {self.backend!r}")
        if self.backend == "mjx" and self.proprio == "reckoned":
            raise ValueError("rl.env.proprio=reckoned runs on rl.env.backend=cpu only (MJX rollouts read proprio true "
                             "or missing)")


# The flat keys of earlier versions -> where they live now (relative to ``rl``): the command line
# refuses an old key naming its new one, and policy / detector checkpoints saved with a flat RL
# config still load (sword_jax.load.section_from_dict).
RENAMED = {
    "policy_width": "policy.width", "policy_layers": "policy.layers", "policy_heads": "policy.heads",
    "max_instruction_bytes": "policy.max_instruction_bytes", "proprio_encoding": "policy.proprio_encoding",
    "sft_steps": "sft.steps", "sft_batch_size": "sft.batch_size", "sft_learning_rate": "sft.learning_rate",
    "sft_episodes_per_task": "sft.episodes_per_task", "sft_lr_end_fraction": "sft.lr_end_fraction",
    "sft_warmup_steps": "sft.warmup_steps", "sft_eval_every": "sft.eval_every",
    "sft_checkpoint_every": "sft.checkpoint_every",
    "reward_model_steps": "reward_model.steps", "reward_model_batch_size": "reward_model.batch_size",
    "reward_model_learning_rate": "reward_model.learning_rate", "reward_labels": "reward_model.labels",
    "positive_tail": "reward_model.positive_tail", "reward_width": "reward_model.width",
    "reward_model_checkpoint_every": "reward_model.checkpoint_every",
    "grpo_steps": "grpo.steps", "rollout_batch": "grpo.rollout_batch", "group_size": "grpo.group_size",
    "learning_rate": "grpo.learning_rate", "clip_low": "grpo.clip_low", "clip_high": "grpo.clip_high",
    "kl_coef": "grpo.kl_coef", "ppo_epochs": "grpo.ppo_epochs", "loss_norm": "grpo.loss_norm",
    "filter_groups": "grpo.filter_groups", "success_bonus": "grpo.success_bonus",
    "temperature": "grpo.temperature", "update_microbatch": "grpo.update_microbatch",
    "eval_every": "grpo.eval_every", "eval_episodes_per_task": "grpo.eval_episodes_per_task",
    "max_chunks": "imagined.max_chunks", "imagined_return": "imagined.return_rule",
    "imagined_execute_steps": "imagined.execute_steps", "imagined_proprio": "imagined.proprio",
    "eval_masked_proprio": "imagined.eval_masked_proprio", "eval_replay_episodes": "imagined.eval_replay_episodes",
    "execute_steps": "env.execute_steps", "action_ensemble": "env.action_ensemble",
    "ensemble_decay": "env.ensemble_decay", "env_proprio": "env.proprio", "env_starts": "env.starts",
}


@dataclasses.dataclass(frozen=True)
class RLConfig:
    """Policy, reward model and GRPO settings: the interface every stage shares, then one section per concern.

    Attributes:
      chunk_len: actions per chunk (= frames the simulator predicts per step).
      action_dim: action dimensions (xyz, rotation, gripper).
      action_bins: discretisation bins per action dimension (OpenVLA: 256).
      image_size: frame size the policy and reward model see (frames are resized to it).
      proprio_dim: proprioceptive state dimensions the environment reports (0 = none).
      success_threshold: reward-model score that counts as success (WoVR: 0.9).
      policy: the policy's architecture (:class:`PolicyConfig`).
      sft: behaviour cloning (:class:`SFTConfig`).
      reward_model: the success detector (:class:`RewardModelConfig`).
      grpo: the GRPO update, its rollouts and evaluations (:class:`GRPOConfig`).
      imagined: rollouts in the learned simulator (:class:`ImaginedConfig`).
      env: acting in the ground-truth environments (:class:`EnvConfig`).
      refresh: refreshing the learned simulator on the moving policy's real episodes (:class:`RefreshConfig`).
      value: the success-probability estimate that closes short GRPO rollouts (:class:`ValueConfig`).
    """

    renamed_fields: ClassVar[dict[str, str]] = RENAMED

    chunk_len: int = 8
    action_dim: int = 7
    action_bins: int = 256
    image_size: int = 64
    proprio_dim: int = 8
    success_threshold: float = 0.9
    policy: PolicyConfig = PolicyConfig()
    sft: SFTConfig = SFTConfig()
    reward_model: RewardModelConfig = RewardModelConfig()
    grpo: GRPOConfig = GRPOConfig()
    imagined: ImaginedConfig = ImaginedConfig()
    env: EnvConfig = EnvConfig()
    refresh: RefreshConfig = RefreshConfig()
    value: ValueConfig = ValueConfig()

    @property
    def detector_image_size(self) -> int:
        """The frame size the success detector reads: ``reward_model.image_size``, else the policy's."""
        return self.reward_model.image_size or self.image_size

    @property
    def imagined_actions_per_decision(self) -> int:
        """Actions a learned simulator executes per policy decision: ``rl.imagined.execute_steps``, else the
        whole chunk."""
        return self.imagined.execute_steps or self.chunk_len

    @property
    def sft_decoded_window(self) -> int:
        """Actions each world-model replay of decoder-aware SFT runs: ``rl.sft.decoded_window``, else an imagined
        rollout's (``rl.imagined.max_chunks x`` :attr:`imagined_actions_per_decision`)."""
        return self.sft.decoded_window or self.imagined.max_chunks * self.imagined_actions_per_decision

    @property
    def imagined_starts_per_step(self) -> int:
        """Start states (GRPO groups) a step in the learned simulator rolls out: ``rl.imagined.oversample x
        rl.grpo.rollout_batch``; the step updates on ``rl.grpo.rollout_batch`` of them."""
        return self.imagined.oversample * self.grpo.rollout_batch

    def validate(self) -> None:
        """Checks each section, then the settings that span sections."""
        for field in dataclasses.fields(self):
            section = getattr(self, field.name)
            if hasattr(section, "validate"):
                section.validate()
        if not 0.0 < self.success_threshold <= 1.0:
            raise ValueError(f"rl.success_threshold must be in (0, 1], got {self.success_threshold}")
        if self.action_bins < 2:
            raise ValueError(f"rl.action_bins must be >= 2, got {self.action_bins}")
        if self.chunk_len < 1:
            raise ValueError(f"rl.chunk_len must be >= 1, got {self.chunk_len}")
        if self.image_size % 8:
            raise ValueError(f"rl.image_size must be a multiple of 8 (three stride-2 convs), got {self.image_size}")
        if self.policy.proprio_encoding == "rot6d" and self.proprio_dim != 8:
            raise ValueError(f"rl.policy.proprio_encoding=rot6d reads the simulator's 8-D proprio; got rl.proprio_dim="
                             f"{self.proprio_dim} (use rl.policy.proprio_encoding=raw)")
        if not 1 <= self.env.execute_steps <= self.chunk_len:
            raise ValueError(f"rl.env.execute_steps must be in [1, rl.chunk_len={self.chunk_len}], got "
                             f"{self.env.execute_steps}")
        executed = self.imagined.execute_steps
        per_chunk = self.imagined_actions_per_decision
        if any(h % per_chunk for h in self.refresh.horizons):
            raise ValueError(f"rl.refresh.horizons must be multiples of the imagined execution ({per_chunk} actions per "
                             f"decision), got {self.refresh.horizons}")
        if executed is not None and (executed < 4 or executed % 4 or self.chunk_len % executed):
            raise ValueError(f"rl.imagined.execute_steps must be a multiple of 4 (one latent frame) dividing "
                             f"rl.chunk_len={self.chunk_len}, got {executed}")
        if self.imagined.guard_on == "verify" and not (self.refresh.every and self.refresh.verify_starts):
            raise ValueError("rl.imagined.guard_on=verify judges the refreshes' checks of imagined rollouts: it needs "
                             "rl.refresh.every > 0 and rl.refresh.verify_starts > 0")
        starts = self.imagined_starts_per_step
        if self.refresh.every and self.refresh.closed_loop_starts % starts:
            raise ValueError(f"rl.refresh.closed_loop_starts={self.refresh.closed_loop_starts} must be a multiple of "
                             f"the starts GRPO draws a step ({starts}): the closed loop's starts are drawn as its are")
        refreshed = self.refresh.every and (self.imagined.reward == "calibrated" or self.refresh.branch)
        if self.imagined.executes and (self.env.backend != "mjx" or refreshed or self.imagined.confirm_success):
            raise ValueError(f"rl.imagined.reward={self.imagined.reward} pays imagined actions by executing them on "
                             "MJX from the keyframes' recorded states: it needs rl.env.backend=mjx, "
                             "rl.imagined.confirm_success=false and no refresh that branches (a refresh's branch "
                             "starts hold no simulator state; calibrated sets its own threshold, so no refresh), "
                             f"got {self.env.backend}, {self.imagined.confirm_success}, rl.refresh.every="
                             f"{self.refresh.every} with branch={self.refresh.branch}")
        if self.env.starts == "branch" and not (self.value.episodes and self.env.backend == "mjx"):
            raise ValueError("rl.env.starts=branch starts GRPO's rollouts at the states of the real episodes collected "
                             "for the value: it needs rl.value.episodes > 0 and rl.env.backend=mjx, got "
                             f"{self.value.episodes} and {self.env.backend!r}")
        if self.value.episodes and self.env.backend != "mjx":
            raise ValueError("rl.value.episodes > 0 closes ground-truth GRPO's rollouts on MJX with a fitted value: it "
                             f"needs rl.env.backend=mjx, got {self.env.backend!r}")
        if self.env.proprio == "reckoned" and self.proprio_dim != 8:
            raise ValueError(f"rl.env.proprio=reckoned integrates the simulator's 8-D proprio; got rl.proprio_dim="
                             f"{self.proprio_dim}")
