"""Flow-matching, data and trainer sections of the experiment config (owned by sword_jax.world_model)."""

import dataclasses
from typing import ClassVar


@dataclasses.dataclass(frozen=True)
class FlowConfig:
    """Flow matching training target, sampler and rollout options."""

    prediction: str = "velocity"  # velocity | epsilon
    num_train_timesteps: int = 1000
    shift: float = 5.0
    sample_steps: int = 5
    guidance_scale: float = 1.0
    pixel_round_trip: bool = False  # WoVR: decode and re-encode between chunks
    context_noise: float = 0.0  # WoVR context-noise augmentation (std); 0 = off
    # share of training segments whose actions are replaced by the null actions (all zeros), the unconditional
    # branch that guidance_scale != 1 contrasts against; 0 = off (the guidance then extrapolates from a branch the
    # model never trained on). Dropped segments write nothing into the DLB cache.
    action_dropout: float = 0.0
    # the sampler's starting noise as a multiple of the prior's (N(0, 1)): 1 = samples of the learned distribution;
    # below 1, lower-temperature samples nearer its centre; 0 = one deterministic prediction per condition (the
    # Euler path from the prior's mean). What a simulator of a deterministic scene may want: every draw of a chunk
    # is a different plausible future, and in closed loop those draws add up decision after decision.
    noise_scale: float = 1.0
    # the shift of the sampler's grid of noise levels (0 = ``shift``, the training's). Wan samples with shift 5 at
    # 50 steps; at a few steps the same shift leaves the last step to jump from a high level (5 steps: 0.56 -> 0,
    # the model's mean estimate from a half-noised state), which blurs what the model cannot tell apart. A smaller
    # sampling shift spends more of the steps at low noise, where the detail is decided (1: a uniform grid).
    sample_shift: float = 0.0

    def validate(self) -> None:
        if self.prediction not in ("velocity", "epsilon"):
            raise ValueError(f"flow.prediction must be velocity|epsilon, got {self.prediction!r}")
        if not self.shift > 0 or self.shift == float("inf") or self.num_train_timesteps <= 0:  # also rejects NaN
            raise ValueError(f"flow.shift and flow.num_train_timesteps must be positive, got {self.shift}/{self.num_train_timesteps}")
        if self.context_noise < 0:
            raise ValueError(f"flow.context_noise must be >= 0, got {self.context_noise}")
        if not 0.0 <= self.action_dropout < 1.0:
            raise ValueError(f"flow.action_dropout must be in [0, 1) (share of segments trained without actions), got "
                             f"{self.action_dropout}")
        if not 0.0 <= self.noise_scale <= 4.0:  # also rejects NaN
            raise ValueError(f"flow.noise_scale must be in [0, 4] (the starting noise's multiple of the prior's), got "
                             f"{self.noise_scale}")
        if not 0.0 <= self.sample_shift <= 100.0:  # also rejects NaN
            raise ValueError(f"flow.sample_shift must be in [0, 100] (0 = flow.shift), got {self.sample_shift}")
        if not 1 <= self.sample_steps <= 50:
            raise ValueError(f"flow.sample_steps must be in [1, 50], got {self.sample_steps}")


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Video segments for world-model training.

    A segment is the episode's first frame, ``context_frames`` context frames and
    ``predict_frames`` future frames (1 + 4 + 8 = 13 by default).

    ``policy_rollouts_per_task``: episodes per task of the supervised policy acting in the simulator
    (sampled actions, fixed length, successes and failures alike) added to the world model's training
    data by the pipeline. Expert episodes alone are ~98% successful, and a world model that never saw
    an attempt fail imagines success under any policy (measured: GRPO inside it then drove real success
    down while imagined success rose). 0 = expert episodes only.

    ``policy_rollout_workers``: processes that record those rollouts (and the held-out ones), each a share
    of the policy's lockstep batches of 32 episodes (worker ``w`` records batches ``w, w + W, ...``, with
    the same keys): the C engine steps a batch's envs one after the other in one process, so more
    processes step more batches at once, and compress their frames side by side. The file is the same,
    bit for bit, for any number; each shares the accelerator (its memory allocated as used, not
    preallocated). Beyond the number of batches there is nothing left to share. 1 = in the stage's process.
    """

    path: str = ""
    # latents of held-out episodes (the layout of ``path``) for the trainer's held-out evaluation
    # (``trainer.eval_every``); the pipeline encodes its held-out expert episodes there, and beside them
    # (``policy_latents``/``policy_actions``) its held-out rollouts of the supervised policy
    heldout_path: str = ""
    num_episodes: int = 16
    episode_frames: int = 65  # 1 + 4k
    image_size: int = 32
    context_frames: int = 4
    predict_frames: int = 8
    batch_size: int = 4
    policy_rollouts_per_task: int = 0
    # held-out rollouts per task of the supervised policy, from the held-out initial states, for the trainer's
    # held-out evaluation (its "policy" segments: the policy's own actions, never trained on); 0 = none
    heldout_policy_rollouts_per_task: int = 0
    policy_rollout_workers: int = 1
    # episodes per task of the expert with time-correlated exploration noise on its motion (std
    # ``exploration_noise`` of an AR(1) process with step-to-step correlation ``exploration_correlation``; the noisy
    # actions are executed and recorded), from training initial states no other file starts from, added to the
    # world model's training data (not the policy's): the arm driven centimetres off the paths the expert and the
    # policy take, and brought back, so the model sees what actions do beyond the rollouts it would otherwise
    # memorise. 0 = none. At the defaults the expert still completes 4 in 20 episodes of 129 steps (C engine, tasks 0,
    # 2, 4, 6, 8 x 4 initial states; 7 in 20 at correlation 0.8, none at noise 0.5; all 20 with DART's 0.1 alone).
    exploration_episodes_per_task: int = 0
    exploration_noise: float = 0.3
    exploration_correlation: float = 0.9
    # settings that change no result (how the work is spread over processes): a run resumes, and a stage is
    # reused, whatever their values
    result_free_fields: ClassVar[tuple[str, ...]] = ("policy_rollout_workers",)

    def validate(self) -> None:
        if (self.episode_frames - 1) % 4 or self.episode_frames < 1:
            raise ValueError(f"data.episode_frames must be of the form 1+4k, got {self.episode_frames}")
        if self.context_frames % 4 or self.predict_frames % 4 or self.context_frames <= 0 or self.predict_frames <= 0:
            raise ValueError(
                f"data.context_frames ({self.context_frames}) and data.predict_frames ({self.predict_frames}) "
                "must be positive multiples of 4 (one latent frame = 4 video frames)"
            )
        if 1 + self.context_frames + self.predict_frames > self.episode_frames:
            raise ValueError(
                f"data: a segment of 1+{self.context_frames}+{self.predict_frames} frames does not fit in "
                f"episodes of {self.episode_frames} frames"
            )
        if self.batch_size <= 0:
            raise ValueError(f"data.batch_size must be positive, got {self.batch_size}")
        if self.policy_rollouts_per_task < 0:
            raise ValueError(f"data.policy_rollouts_per_task must be >= 0, got {self.policy_rollouts_per_task}")
        if self.heldout_policy_rollouts_per_task < 0:
            raise ValueError("data.heldout_policy_rollouts_per_task must be >= 0, got "
                             f"{self.heldout_policy_rollouts_per_task}")
        if self.policy_rollout_workers < 1:
            raise ValueError(f"data.policy_rollout_workers must be >= 1 (1 = in the stage's process), got "
                             f"{self.policy_rollout_workers}")
        if self.exploration_episodes_per_task < 0:
            raise ValueError(f"data.exploration_episodes_per_task must be >= 0, got {self.exploration_episodes_per_task}")
        if not 0 <= self.exploration_noise <= 1 or not 0 <= self.exploration_correlation < 1:  # also reject NaN
            raise ValueError(f"data.exploration_noise must be in [0, 1] and data.exploration_correlation in [0, 1), got "
                             f"{self.exploration_noise} and {self.exploration_correlation}")


@dataclasses.dataclass(frozen=True)
class TrainerConfig:
    """Optimiser and loop settings of the world-model trainer."""

    steps: int = 100
    learning_rate: float = 1e-4
    warmup_steps: int = 10
    lr_schedule: str = "constant"  # constant | cosine (after the linear warmup)
    lr_end_fraction: float = 0.1  # cosine: final lr / peak lr
    weight_decay: float = 0.01
    adam_b1: float = 0.9
    adam_b2: float = 0.999
    adam_eps: float = 1e-8
    adam_mu_dtype: str = "float32"  # float32 | bfloat16: Adam's first moment (optax mu_dtype); the second stays float32
    grad_clip: float = 1.0  # global-norm clip; 0 = off
    ema_decay: float = 0.0  # 0 = no EMA
    log_every: int = 10
    checkpoint_every: int = 50
    keep_checkpoints: int = 2
    on_nonfinite: str = "stop"  # stop | skip
    # held-out evaluation (sword_jax.world_model.heldout): every eval_every steps (a multiple of log_every; the
    # last step too; 0 = off) the flow loss and the sampler's error on eval_batches fixed batches of held-out and
    # of training segments, the sampler at each of eval_sample_steps Euler steps (empty: flow.sample_steps)
    eval_every: int = 0
    eval_batches: int = 2
    eval_sample_steps: tuple[int, ...] = ()
    # with eval_every: at the run's end, every fixed segment's own sample error too (heldout_segments.json in the
    # run's folder; where in the episodes a split's error lies)
    eval_segments: bool = False

    def validate(self) -> None:
        if self.steps < 0 or self.warmup_steps < 0:
            raise ValueError(f"trainer.steps/warmup_steps must be >= 0, got {self.steps}/{self.warmup_steps}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"trainer.ema_decay must be in [0, 1), got {self.ema_decay}")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ValueError(f"trainer.lr_schedule must be constant|cosine, got {self.lr_schedule!r}")
        if self.learning_rate <= 0 or self.grad_clip < 0:
            raise ValueError(f"trainer.learning_rate must be > 0 and grad_clip >= 0, got {self.learning_rate}/{self.grad_clip}")
        if self.log_every <= 0 or self.checkpoint_every <= 0 or self.keep_checkpoints <= 0:
            raise ValueError("trainer.log_every, checkpoint_every and keep_checkpoints must be positive")
        if self.adam_mu_dtype not in ("float32", "bfloat16"):
            raise ValueError(f"trainer.adam_mu_dtype must be float32|bfloat16, got {self.adam_mu_dtype!r}")
        if self.on_nonfinite not in ("stop", "skip"):
            raise ValueError(f"trainer.on_nonfinite must be stop|skip, got {self.on_nonfinite!r}")
        if self.eval_every < 0 or (self.eval_every and self.eval_every % self.log_every):
            raise ValueError(f"trainer.eval_every must be 0 (off) or a positive multiple of trainer.log_every "
                             f"({self.log_every}): the evaluation is read with a log step's metrics; got {self.eval_every}")
        if self.eval_batches <= 0:
            raise ValueError(f"trainer.eval_batches must be positive, got {self.eval_batches}")
        if any(not 1 <= n <= 50 for n in self.eval_sample_steps) or len(set(self.eval_sample_steps)) != len(
                self.eval_sample_steps):
            raise ValueError(f"trainer.eval_sample_steps must be distinct Euler step counts in [1, 50], got "
                             f"{self.eval_sample_steps}")
