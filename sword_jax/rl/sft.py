"""Supervised fine-tuning (behaviour cloning) of the VLA policy on expert demonstrations.

The loss is the cross-entropy of the expert's binned actions under the policy's per-token
categoricals (OpenVLA's objective). Proprio is dropped (marked invalid) for a fraction of the
samples so the policy also acts when a learned simulator cannot report proprio. The starting
point for GRPO is set by ``rl.sft.steps`` and ``rl.sft.episodes_per_task`` (how many
demonstrations per task it sees).

Decoder-aware SFT (``rl.sft.decoded_fraction``): a share of each batch's frames comes from the episodes
round-tripped through the world model's VAE (:mod:`sword_jax.rl.decoded_frames`), so the policy also reads the
frames GRPO in the world model will show it. For example, fine-tuning a trained policy on half decoded frames::

    python -m benchmarks.bench_policy sft --config sword:small --out runs/p --tag _dec --demos-per-task 50 \\
        --execute ens --workers 14 --eval-episodes 50 \\
        --rl.sft.init=runs/p/policy_d50.npz --rl.sft.decoded_fraction=0.5 --vae runs/rsv/pipeline/vae_run/vae \\
        --rl.sft.steps=1000

With ``rl.sft.decoded_source=world_model`` those frames are the world model's own: each demonstration's actions
replayed in it from its real frames (:mod:`sword_jax.rl.imagined_frames`), each frame labelled with the
demonstration's action at that step.
"""

from __future__ import annotations

import operator
from typing import Any

import jax
import jax.numpy as jnp
import optax
import numpy as np
from flax import nnx, struct

from sword_jax import optim
from sword_jax import sharding as shd
from sword_jax.rl import data as rl_data
from sword_jax.rl.config import RLConfig
from sword_jax.rl.image_aug import augment_frames
from sword_jax.rl.policy import (actions_to_tokens, resize_frames, token_log_probs, tokens_to_actions,
                                 trainable_mask)
from sword_jax.rng import stream_rng

PROPRIO_DROPOUT = 0.3
# RL config keys (paths under ``rl``) a resumed SFT run must share with its checkpoint (others may change
# between runs)
SFT_RUN_KEYS = ("sft.batch_size", "sft.learning_rate", "sft.warmup_steps", "sft.lr_end_fraction", "chunk_len",
                "action_bins", "image_size")


@struct.dataclass
class SFTState:
    params: Any
    opt_state: Any
    step: jax.Array


def sft_schedule(cfg: RLConfig, total_steps: int) -> optax.Schedule:
    """Linear warm-up to ``sft_learning_rate``, then cosine decay to ``sft_lr_end_fraction`` of it.

    The end is a fraction of the peak (optax's ``warmup_cosine_decay_schedule`` takes an absolute
    end value: passing 0.1 there once made the rate climb to 0.1 over the run).
    """
    steps = max(int(total_steps), 1)
    warmup = min(cfg.sft.warmup_steps, steps // 10)
    return optim.learning_rate_schedule(cfg.sft.learning_rate, warmup_steps=warmup, kind="cosine", total_steps=steps,
                                        end_fraction=cfg.sft.lr_end_fraction)


def make_sft_optimizer(schedule: optax.Schedule) -> optax.GradientTransformation:
    """Global-norm clipping at 1, then AdamW (weight decay 1e-4, none on the policy's stored statistics)."""
    return optim.make_optimizer(schedule, weight_decay=1e-4, grad_clip=1.0, decay_mask=trainable_mask)


def _sft_loss(graphdef: nnx.GraphDef, cfg: RLConfig, params, batch, proprio_valid, augment_key=None):
    frames = resize_frames(batch["frames"], cfg.image_size)
    if augment_key is not None:  # rl.sft.image_aug: the training batch only
        frames = augment_frames(frames, augment_key)
    targets = actions_to_tokens(batch["actions"], cfg.action_bins)
    logits = nnx.merge(graphdef, params)(frames, batch["instruction_tokens"], batch["proprio"], proprio_valid)
    logp = token_log_probs(logits, targets)
    correct = (jnp.argmax(logits, -1) == targets).astype(jnp.float32)
    # mean |error| of the argmax action in action units (bin centres), what execution feels
    action_error = jnp.mean(jnp.abs(tokens_to_actions(jnp.argmax(logits, -1), cfg.action_bins)
                                    - jnp.clip(batch["actions"], -1.0, 1.0)))
    return -jnp.mean(logp), {"token_accuracy": jnp.mean(correct), "action_l1": action_error}


def make_sft_eval(graphdef: nnx.GraphDef, cfg: RLConfig):
    """Jitted ``evaluate(params, batch) -> metrics``: teacher-forced loss, token accuracy and action
    L1 on a batch (held-out demonstrations), with proprio present."""

    @jax.jit
    def evaluate(params, batch):
        b = batch["frames"].shape[0]
        loss, metrics = _sft_loss(graphdef, cfg, params, batch, jnp.ones((b,), jnp.float32))
        return dict(metrics, loss=loss)

    return evaluate


def make_sft_step(graphdef: nnx.GraphDef, cfg: RLConfig, *, total_steps: int | None = None, mesh=None,
                  rules=shd.DEFAULT_RULES):
    """``init(params) -> SFTState`` and the compiled ``step(state, batch, key) -> (state, metrics)``.

    ``batch``: ``frames [b, H, W, 3]`` (uint8 or float in [0, 1]), ``instruction_tokens [b, L]``,
    ``proprio [b, P]``, ``actions [b, chunk_len, action_dim]`` in [-1, 1]. The step is compiled by
    :func:`sword_jax.sharding.compile_step` over ``mesh`` (default: one device): the batch split
    over its leading dim, the state donated and kept where it was placed (else replicated).
    """
    schedule = sft_schedule(cfg, total_steps or cfg.sft.steps)
    optimizer = make_sft_optimizer(schedule)

    def init(params) -> SFTState:
        return SFTState(params, optimizer.init(params), jnp.zeros((), jnp.int32))

    def step(state: SFTState, batch, key):
        key = jax.random.fold_in(key, state.step)
        b = batch["frames"].shape[0]
        proprio_valid = (jax.random.uniform(key, (b,)) >= PROPRIO_DROPOUT).astype(jnp.float32)
        augment_key = jax.random.fold_in(key, 1) if cfg.sft.image_aug else None

        def loss_fn(params):
            return _sft_loss(graphdef, cfg, params, batch, proprio_valid, augment_key)

        (loss, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        _, opt_state, params = optim.apply_optimizer(optimizer, grads, state.opt_state, state.params)
        learning_rate = optim.learning_rate_at(schedule, state.step)
        return SFTState(params, opt_state, state.step + 1), dict(
            metrics, loss=loss, grad_norm=optax.global_norm(grads), learning_rate=learning_rate)

    return init, shd.compile_step(step, shd.default_mesh(mesh), rules)


def decoded_samples(seed: int, step: int, batch_size: int, fraction: float) -> np.ndarray:
    """``[batch_size]`` bool: which samples of step ``step``'s SFT batch read the VAE's round trip of their frame
    (``rl.sft.decoded_fraction``): ``round(fraction * batch_size)`` of them, drawn from stream
    ``sft/decoded_frames`` of ``(seed, step)``, so a resumed run draws the same ones."""
    chosen = np.zeros(batch_size, bool)
    count = int(round(fraction * batch_size))
    if count:
        chosen[stream_rng(seed, "sft/decoded_frames", step).permutation(batch_size)[:count]] = True
    return chosen


def sft_batch_at(episodes: rl_data.EpisodeSet, cfg: RLConfig, seed: int, step: int,
                 decoded_frames: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The training batch of 0-based step ``step``: :func:`sword_jax.rl.data.sample_bc_batch` from stream
    ``sft/batches`` of ``(seed, step)``; with ``decoded_frames`` (``[E, T, H, W, 3]`` like ``episodes.frames``) the
    samples :func:`decoded_samples` picks take their frame from it (same episode, same step)."""
    ep, t = rl_data.bc_batch_index(episodes, cfg.sft.batch_size, stream_rng(seed, "sft/batches", step))
    batch = rl_data.bc_batch_at(episodes, ep, t, cfg.chunk_len, cfg.policy.max_instruction_bytes)
    if decoded_frames is not None:
        chosen = decoded_samples(seed, step, cfg.sft.batch_size, cfg.sft.decoded_fraction)
        batch["frames"] = np.where(chosen[:, None, None, None], decoded_frames[ep, t], batch["frames"])
    return batch


def train_sft(
    graphdef: nnx.GraphDef,
    params: Any,
    cfg: RLConfig,
    train_episodes: Any,
    held_out: Any = None,
    *,
    seed: int = 0,
    steps: int | None = None,
    log: Any = print,
    checkpoint_dir: str | None = None,
    mesh=None,
    rules=shd.DEFAULT_RULES,
    decoded_frames: np.ndarray | None = None,
    fit_proprio_stats: bool = True,
) -> tuple[Any, list[dict[str, float]]]:
    """Behaviour cloning on ``train_episodes`` (an ``rl.data.EpisodeSet``) from ``params``.

    The proprio normalisation is set from the training demonstrations before the first step (unless
    ``fit_proprio_stats`` is False: fine-tuning a trained policy keeps its own). The
    batch of step ``s`` is :func:`sft_batch_at` (drawn from ``stream_rng(seed, "sft/batches", s)``), so with
    ``checkpoint_dir`` the run saves its train state every ``cfg.sft.checkpoint_every`` steps and
    resumes from there bit-exactly (see :func:`sword_jax.train_loop.run_steps`). Every
    ``cfg.sft.eval_every`` steps (and at the end) the teacher-forced loss, token accuracy and action
    L1 on ``held_out`` demonstrations are logged next to the training batch's, one step late.

    ``mesh`` / ``rules``: where the step runs (see :func:`make_sft_step`).

    ``decoded_frames``: ``[E, T, H, W, 3]`` uint8, ``train_episodes.frames`` after the VAE's round trip
    (:func:`sword_jax.rl.decoded_frames.round_trip_episodes`), read by ``cfg.sft.decoded_fraction`` of each
    training batch's samples; needed exactly when that fraction is above 0. Held-out metrics use real frames.

    Returns:
      ``(params, history)``: the trained parameters and one dict of metrics per log point (those
      before a resume come from the checkpoint).

    Raises:
      ValueError: ``decoded_frames`` missing while ``cfg.sft.decoded_fraction > 0``, given while it is 0, or not
        shaped like ``train_episodes.frames``.
      sword_jax.train_loop.NonFiniteLoss: a non-finite loss or gradient (a ``FloatingPointError``
        naming the 0-based step; the last good checkpoint is kept).
    """
    from sword_jax.rl.policy import compute_proprio_stats, set_proprio_stats
    from sword_jax.train_loop import run_steps

    fraction = cfg.sft.decoded_fraction
    if fraction > 0 and decoded_frames is None:
        raise ValueError(f"train_sft: rl.sft.decoded_fraction={fraction} needs decoded_frames (the training episodes "
                         "round-tripped through the VAE, sword_jax.rl.decoded_frames.round_trip_episodes)")
    if decoded_frames is not None:
        if fraction <= 0:
            raise ValueError("train_sft: decoded_frames given but rl.sft.decoded_fraction is 0 (they would not be read)")
        if decoded_frames.shape != train_episodes.frames.shape or decoded_frames.dtype != np.uint8:
            raise ValueError(f"train_sft: decoded_frames must be uint8 shaped like the training frames "
                             f"{train_episodes.frames.shape}, got {decoded_frames.shape} {decoded_frames.dtype}")
    steps = steps or cfg.sft.steps
    if fit_proprio_stats:
        valid_steps = np.concatenate([train_episodes.proprio[e, : train_episodes.lengths[e]]
                                      for e in range(train_episodes.num_episodes)])
        params = set_proprio_stats(params, compute_proprio_stats(valid_steps, cfg))
    init, step = make_sft_step(graphdef, cfg, total_steps=steps, mesh=mesh, rules=rules)
    evaluate = make_sft_eval(graphdef, cfg)
    held_batches = []
    if held_out is not None:
        held_rng = stream_rng(seed, "sft/held_out_batches")
        held_batches = [rl_data.sample_bc_batch(held_out, cfg.sft.batch_size, cfg.chunk_len, cfg.policy.max_instruction_bytes,
                                                held_rng) for _ in range(4)]

    def batch_at(i: int) -> dict:
        return sft_batch_at(train_episodes, cfg, seed, i, decoded_frames)

    def report(done: int, metrics: dict[str, float], held: list, eta: float) -> dict[str, float]:
        point = {"step": done, **metrics}
        for batch_metrics in held:
            for name, value in batch_metrics.items():
                point[f"heldout_{name}"] = point.get(f"heldout_{name}", 0.0) + float(value) / len(held)
        held_line = (f" | held-out loss {point['heldout_loss']:.3f} acc {point['heldout_token_accuracy']:.3f} "
                     f"L1 {point['heldout_action_l1']:.3f}") if held else ""
        log(f"sft step {done}/{steps} loss {point['loss']:.3f} acc {point['token_accuracy']:.3f} "
            f"lr {point['learning_rate']:.2e}{held_line} eta {eta:.0f}s")
        return point

    run_id = {"seed": seed, "steps": steps, "demonstrations": int(train_episodes.num_episodes),
              **{f"rl.{k}": operator.attrgetter(k)(cfg) for k in SFT_RUN_KEYS},
              # named only when on: older runs resume
              **({"rl.sft.image_aug": True} if cfg.sft.image_aug else {}),
              **({"rl.sft.decoded_fraction": fraction} if fraction > 0 else {}),
              **({} if fit_proprio_stats else {"fit_proprio_stats": False})}
    result = run_steps(step, init(params), batch_at, key=jax.random.key(seed), steps=steps,
                       log_every=cfg.sft.eval_every, name="SFT", report=report,
                       observe=lambda state: [evaluate(state.params, hb) for hb in held_batches],
                       checkpoint_dir=checkpoint_dir, checkpoint_every=cfg.sft.checkpoint_every, run_id=run_id, log=log)
    return result.state.params, result.history
