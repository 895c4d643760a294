"""The one optimizer builder every trainer uses (VAE, world model, GRPO, SFT, reward model).

``learning_rate_schedule`` is a linear warm-up from 0 followed by a constant rate or a cosine decay
to a fraction of the peak; ``make_optimizer`` chains optional global-norm clipping with AdamW
(betas, eps, weight decay, an optional weight-decay mask). ``apply_optimizer`` and
``learning_rate_at`` hold the one workaround for optax under strict dtype promotion;
``apply_finite_update`` is the one finite gate (a non-finite loss or gradient skips the update).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax

SCHEDULE_KINDS = ("constant", "cosine")


def learning_rate_schedule(
    peak: float, *, warmup_steps: int = 0, kind: str = "constant", total_steps: int = 0, end_fraction: float = 0.0,
) -> optax.Schedule:
    """Linear warm-up from 0 to ``peak`` over ``warmup_steps``, then constant or cosine decay.

    Args:
      peak: the learning rate after the warm-up.
      warmup_steps: length of the linear warm-up (0: none).
      kind: ``constant`` or ``cosine``.
      total_steps: cosine only: the schedule (warm-up included) reaches ``end_fraction * peak`` here.
      end_fraction: cosine only: final rate / peak rate (optax's ``alpha``, not an absolute value).
    """
    if kind not in SCHEDULE_KINDS:
        raise ValueError(f"learning_rate_schedule: kind must be one of {SCHEDULE_KINDS}, got {kind!r}")
    if warmup_steps < 0:
        raise ValueError(f"learning_rate_schedule: warmup_steps must be >= 0, got {warmup_steps}")
    if kind == "cosine":
        after = optax.cosine_decay_schedule(peak, max(total_steps - warmup_steps, 1), alpha=end_fraction)
    else:
        after = optax.constant_schedule(peak)
    if warmup_steps == 0:
        return after
    warmup = optax.linear_schedule(0.0, peak, warmup_steps)
    return optax.join_schedules([warmup, after], [warmup_steps])


def make_optimizer(
    learning_rate: float | optax.Schedule,
    *,
    weight_decay: float,
    b1: float = 0.9,
    b2: float = 0.999,
    eps: float = 1e-8,
    grad_clip: float = 0.0,
    decay_mask: Any | Callable[[Any], Any] | None = None,
    mu_dtype: Any = None,
) -> optax.GradientTransformation:
    """Optional global-norm clipping, then AdamW.

    Args:
      learning_rate: a constant (no schedule state) or a schedule from :func:`learning_rate_schedule`.
      weight_decay: decoupled AdamW weight decay.
      b1 / b2 / eps: Adam moments and denominator epsilon.
      grad_clip: global-norm clip of the gradients; 0 disables it.
      decay_mask: pytree of bools (or a function of the params returning one): False leaves are
        not decayed (e.g. :func:`sword_jax.rl.policy.trainable_mask`).
      mu_dtype: dtype of Adam's first moment (None: the parameters'). ``bfloat16`` halves its memory;
        the second moment stays in the parameters' dtype (an EMA at ``b2 = 0.999`` moves by 0.1% a
        step, below bfloat16's resolution of about 0.4%, so it could not decay there).

    Returns:
      ``optax.chain`` of the parts (its state is a tuple, one entry per part).
    """
    if grad_clip < 0:
        raise ValueError(f"make_optimizer: grad_clip must be >= 0, got {grad_clip}")
    parts = []
    if grad_clip > 0:
        parts.append(optax.clip_by_global_norm(grad_clip))
    parts.append(optax.adamw(learning_rate, b1=b1, b2=b2, eps=eps, weight_decay=weight_decay, mask=decay_mask,
                             mu_dtype=mu_dtype))
    return optax.chain(*parts)


def apply_optimizer(optimizer: optax.GradientTransformation, grads: Any, opt_state: Any, params: Any
                    ) -> tuple[Any, Any, Any]:
    """One optimizer update; returns ``(updates, opt_state, params)``.

    optax mixes Python floats with its int32 step count, which strict dtype promotion rejects; the
    update alone runs under standard promotion.
    """
    with jax.numpy_dtype_promotion("standard"):
        updates, opt_state = optimizer.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
    return updates, opt_state, params


def apply_finite_update(optimizer: optax.GradientTransformation, loss: jax.Array, grads: Any, opt_state: Any,
                        params: Any) -> tuple[Any, Any, Any, jax.Array]:
    """:func:`apply_optimizer`, skipped when the loss or the gradient norm is non-finite.

    Returns ``(updates, opt_state, params, finite)``: where ``finite`` is False the optimizer state
    and parameters come back unchanged, so NaN never reaches them (or a checkpoint).
    """
    updates, new_opt_state, new_params = apply_optimizer(optimizer, grads, opt_state, params)
    finite = jnp.isfinite(loss) & jnp.isfinite(optax.global_norm(grads))
    keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(finite, a, b), new, old)  # noqa: E731
    return updates, keep(new_opt_state, opt_state), keep(new_params, params), finite


def learning_rate_at(schedule: optax.Schedule, step: jax.Array | int) -> jax.Array:
    """``schedule(step)`` as a float32 scalar (for metrics), under the same promotion workaround."""
    with jax.numpy_dtype_promotion("standard"):
        return jnp.asarray(schedule(step), jnp.float32)
