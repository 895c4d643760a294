"""Supervised fine-tuning (behaviour cloning) of the VLA policy on expert demonstrations.

The loss is the cross-entropy of the expert's binned actions under the policy's per-token
categoricals (OpenVLA's objective). Proprio is dropped (marked invalid) for a fraction of the
samples so the policy also acts when a learned simulator cannot report proprio. The starting
point for GRPO is set by ``rl.sft_steps`` and ``rl.sft_episodes_per_task`` (how many
demonstrations per task it sees).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import nnx, struct

from sword_jax.rl.config import RLConfig
from sword_jax.rl.grpo import apply_optimizer
from sword_jax.rl.policy import actions_to_tokens, resize_frames, token_log_probs

PROPRIO_DROPOUT = 0.3


@struct.dataclass
class SFTState:
    params: Any
    opt_state: Any
    step: jax.Array


def make_sft_step(graphdef: nnx.GraphDef, cfg: RLConfig, *, total_steps: int | None = None):
    """``init(params) -> SFTState`` and jitted ``step(state, batch, key) -> (state, metrics)``.

    ``batch``: ``frames [b, H, W, 3]`` (uint8 or float in [0, 1]), ``instruction_tokens [b, L]``,
    ``proprio [b, P]``, ``actions [b, chunk_len, action_dim]`` in [-1, 1].
    """
    steps = max(total_steps or cfg.sft_steps, 1)
    schedule = optax.warmup_cosine_decay_schedule(0.0, cfg.sft_learning_rate, min(50, steps // 10 + 1), steps, 0.1)
    optimizer = optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=1e-4))

    def init(params) -> SFTState:
        return SFTState(params, optimizer.init(params), jnp.zeros((), jnp.int32))

    def step(state: SFTState, batch, key):
        key = jax.random.fold_in(key, state.step)
        frames = resize_frames(batch["frames"], cfg.image_size)
        b = frames.shape[0]
        proprio_valid = (jax.random.uniform(key, (b,)) >= PROPRIO_DROPOUT).astype(jnp.float32)
        targets = actions_to_tokens(batch["actions"], cfg.action_bins)

        def loss_fn(params):
            logits = nnx.merge(graphdef, params)(frames, batch["instruction_tokens"], batch["proprio"], proprio_valid)
            logp = token_log_probs(logits, targets)
            acc = jnp.mean((jnp.argmax(logits, -1) == targets).astype(jnp.float32))
            return -jnp.mean(logp), acc

        (loss, acc), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        _, opt_state, params = apply_optimizer(optimizer, grads, state.opt_state, state.params)
        return SFTState(params, opt_state, state.step + 1), {"loss": loss, "token_accuracy": acc,
                                                            "grad_norm": optax.global_norm(grads)}

    return init, jax.jit(step, donate_argnums=(0,))
