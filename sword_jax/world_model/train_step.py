"""The world-model train step: teacher forcing, plus Dynamic Latent Bootstrapping when enabled.

``step(state, batch, key) -> (state, metrics)`` is pure. ``key`` is the run's root key; the step
folds in ``state.step`` and splits named keys, so a resumed run draws the same numbers.

Batch (global arrays, sharded over ``batch``): ``latents [b, 1 + k + p, h, w, c]`` (first frame,
k context, p future latents), ``actions [b, 1 + 4(k + p), a]``, ``episode [b]`` and ``start [b]``
(latent-frame index of the first context latent), as produced by
:class:`sword_jax.world_model.data.SegmentLoader`. An optional ``given_context [b]`` (bool) marks rows whose
context is given and must be trained on as it is (the world model's own closed-loop latents,
:mod:`sword_jax.rl.closed_loop`): the cache neither replaces their context nor takes their predictions.

With the cache enabled the step (1) reads: replaces context latents by cached predictions with
probability ``read_prob(step)`` where filled; (2) trains exactly like teacher forcing on that
context; (3) writes back into the future slots either the clean future estimate implied by the
training forward pass (``cache.write_source=one_step``) or the flow sampler's output on the same
conditioning (``sampler``: no gradient, ``cache.write_sample_steps`` Euler steps), see
:mod:`sword_jax.world_model.cache_fidelity`. With read probability 0 it is bitwise the teacher-forcing step. A
non-finite loss or gradient skips the update and the cache write and records the step in
``state.first_nonfinite_step``.

On log steps (``(step + 1) % trainer.log_every == 0`` or the last step) with
``cache.log_inference_distance``, the step also samples what inference would put in the context for
the written latents and reports ``cache_vs_inference_{rel_mse,cosine,norm_ratio}`` (NaN on other
steps: the sampler runs under ``lax.cond``, so unlogged steps do not pay for it).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import optax
from flax import nnx
from jax.sharding import Mesh, NamedSharding

from sword_jax import optim
from sword_jax import sharding as shd
from sword_jax.dlb import cache as dlb_cache
from sword_jax.world_model import cache_fidelity as dlb_fidelity
from sword_jax.dlb import schedule as dlb_schedule
from sword_jax.dlb.config import CacheConfig
from sword_jax.rng import stream_key
from sword_jax.world_model import flow, sampler
from sword_jax.world_model.config import FlowConfig, TrainerConfig
from sword_jax.world_model.train_state import TrainState, world_model_optimizer

StepFn = Callable[[TrainState, dict, jax.Array], tuple[TrainState, dict]]


STEP_KEY_NAMES = ("noise", "sigma", "context_noise", "read", "write")
# the stream of the write key whose noise makes the inference reference of the cache_vs_inference metrics
INFERENCE_STREAM = "dlb/inference_reference"
# the stream of the step's key that draws flow.action_dropout's segments (apart from STEP_KEY_NAMES, so a run
# without it draws every other key as before)
ACTION_DROPOUT_STREAM = "world_model/action_dropout"


def step_keys(root: jax.Array, step: jax.Array | int) -> dict[str, jax.Array]:
    """The named keys of step ``step`` (0-based): ``fold_in(root, step)`` split in ``STEP_KEY_NAMES``
    order. ``write`` draws the ``sampler`` write source's noise; its stream ``INFERENCE_STREAM`` the
    inference reference of the ``cache_vs_inference_*`` metrics."""
    return dict(zip(STEP_KEY_NAMES, jax.random.split(jax.random.fold_in(root, step), len(STEP_KEY_NAMES))))


def make_train_step(
    graphdef: nnx.GraphDef,
    *,
    flow_cfg: FlowConfig,
    trainer_cfg: TrainerConfig,
    cache_cfg: CacheConfig,
    num_context: int,
    num_episodes: int | None = None,
) -> StepFn:
    """Builds the pure train step (not yet jitted; see :func:`compile_train_step`).

    Args:
      graphdef: static graph of the world model (``model(latents, timesteps, actions)``).
      flow_cfg: training target, shift and context-noise augmentation.
      trainer_cfg: optimiser and EMA settings (must match those used to create the state).
      cache_cfg: DLB settings; ``enabled=False`` gives plain teacher forcing.
      num_context: context latents ``k`` per segment.
      num_episodes: real episodes of the dataset (for the ``cache_filled`` metric).
    """
    tx = world_model_optimizer(trainer_cfg)
    num_cond = 1 + num_context
    use_cache = cache_cfg.enabled

    def _inference_distance(step_index, written, model_fn, cond_latents, actions, *, key):
        """``cache_vs_inference_*`` on log steps (the host reads step ``step_index + 1``), NaN otherwise."""
        steps_done = step_index + 1
        is_log_step = (steps_done % trainer_cfg.log_every == 0) | (steps_done == trainer_cfg.steps)
        cached = dlb_fidelity.stored(written[:, :dlb_fidelity.num_written(cache_cfg, written.shape[1])], cache_cfg)

        def measure():
            reference = dlb_fidelity.inference_context(flow_cfg, model_fn, cond_latents, actions, key=key,
                                                       num_future=written.shape[1])
            return dlb_fidelity.latent_distance(cached, reference[:, :cached.shape[1]])

        def skip():
            return {name: jnp.float32(jnp.nan) for name in dlb_fidelity.DISTANCE_METRICS}

        distance = jax.lax.cond(is_log_step, measure, skip)
        return {f"cache_vs_inference_{name}": value for name, value in distance.items()}

    def step(state: TrainState, batch: dict, key: jax.Array) -> tuple[TrainState, dict]:
        keys = step_keys(key, state.step)
        noise_key, sigma_key, context_noise_key, read_key, write_key = (keys[n] for n in STEP_KEY_NAMES)
        latents = batch["latents"].astype(jnp.float32)
        actions = batch["actions"].astype(jnp.float32)
        batch_size = latents.shape[0]
        if latents.shape[1] <= num_cond:
            raise ValueError(f"train step: segments of {latents.shape[1]} latents leave no future after {num_cond}")
        first, context, future = latents[:, :1], latents[:, 1:num_cond], latents[:, num_cond:]
        metrics: dict[str, jax.Array] = {}

        if use_cache:
            read_prob = dlb_schedule.read_prob(cache_cfg, state.step)
            context_frames = batch["start"][:, None] + jnp.arange(num_context, dtype=jnp.int32)[None, :]
            given = batch.get("given_context")
            given_context = context
            context, read_mask = dlb_cache.read_context(
                state.cache, context, batch["episode"], context_frames, read_prob, key=read_key)
            if given is not None:  # rows whose context is the point of the segment: never replaced
                read_mask = read_mask & ~given[:, None]
                context = jnp.where(given[:, None, None, None, None], given_context, context)
            metrics["read_prob"] = read_prob
            metrics["read_share"] = jnp.mean(jnp.any(read_mask, axis=1).astype(jnp.float32))
        if flow_cfg.context_noise > 0:
            context = context + jnp.float32(flow_cfg.context_noise) * jax.random.normal(
                context_noise_key, context.shape, jnp.float32)

        segment = jnp.concatenate([first, context, future], axis=1)
        sigma = flow.sample_sigmas(batch_size, flow_cfg, key=sigma_key)
        noise = jax.random.normal(noise_key, future.shape, jnp.float32)
        model_input, timesteps = flow.noisy_segment(segment, noise, sigma, num_cond, flow_cfg)
        trained_actions, write_enabled = actions, None
        if use_cache and batch.get("given_context") is not None:  # their slots are not this dataset's: no write
            write_enabled = ~batch["given_context"]
        if flow_cfg.action_dropout > 0:  # classifier-free guidance's unconditional branch, trained on a share
            dropped = jax.random.bernoulli(stream_key(jax.random.fold_in(key, state.step), ACTION_DROPOUT_STREAM),
                                           flow_cfg.action_dropout, (batch_size,))
            trained_actions = jnp.where(dropped[:, None, None], sampler.null_actions(actions), actions)
            write_enabled = ~dropped if write_enabled is None else write_enabled & ~dropped
            metrics["action_dropped"] = jnp.mean(dropped.astype(jnp.float32))

        def loss_fn(params):
            prediction = nnx.merge(graphdef, params, state.buffers)(model_input, timesteps, trained_actions)
            return flow.flow_loss(prediction, segment, noise, num_cond, flow_cfg), prediction

        (loss, prediction), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        grad_norm = optax.global_norm(grads)
        updates, opt_state, params, finite = optim.apply_finite_update(tx, loss, grads, state.opt_state, state.params)
        ema_params = state.ema_params
        if ema_params is not None:
            decay = jnp.float32(trainer_cfg.ema_decay)
            ema_params = jax.tree.map(lambda e, p: decay * e + (jnp.float32(1.0) - decay) * p, ema_params, params)

        cache = state.cache
        if use_cache:
            # The model at the step's pre-update params: the one that made the training prediction.
            model_fn = sampler.model_fn_from_state(graphdef, (jax.lax.stop_gradient(state.params), state.buffers))
            cond_latents = segment[:, :num_cond]
            written = dlb_fidelity.write_latents(
                cache_cfg, flow_cfg, model_fn, cond_latents, actions, key=write_key,
                prediction_future=prediction[:, num_cond:], noisy_future=model_input[:, num_cond:], sigma=sigma)
            cache = dlb_cache.write_predictions(
                cache, cache_cfg, written, batch["episode"], batch["start"] + num_context,
                enabled=finite if write_enabled is None else finite & write_enabled)
            if cache_cfg.log_inference_distance:
                metrics.update(_inference_distance(
                    state.step, written, model_fn, cond_latents, actions, key=stream_key(write_key, INFERENCE_STREAM)))
            if num_episodes is not None:
                metrics["cache_filled"] = dlb_cache.filled_fraction(cache, num_episodes)

        first_nonfinite = jnp.where(~finite & (state.first_nonfinite_step < 0), state.step, state.first_nonfinite_step)
        metrics.update(
            loss=loss,
            grad_norm=grad_norm,
            param_norm=optax.global_norm(params),
            update_norm=optax.global_norm(updates) * finite.astype(jnp.float32),
            nonfinite=(~finite).astype(jnp.int32),
            first_nonfinite_step=first_nonfinite.astype(jnp.int32),
        )
        new_state = TrainState(
            step=state.step + 1, params=params, buffers=state.buffers, opt_state=opt_state,
            ema_params=ema_params, cache=cache, first_nonfinite_step=first_nonfinite.astype(jnp.int32),
        )
        return new_state, metrics

    return step


def step_was_finite(metrics: dict) -> jax.Array:
    """Whether a step's loss and gradient were finite: its own ``nonfinite`` flag (its other metrics may be
    NaN by design, e.g. ``cache_vs_inference_*`` between log steps). The ``metrics_finite`` of
    :func:`sword_jax.train_loop.run_steps` for every world-model training loop."""
    return metrics["nonfinite"] == 0


def compile_train_step(
    step_fn: StepFn,
    state_shardings: TrainState,
    batch_shardings: dict[str, NamedSharding],
    mesh: Mesh,
    rules=shd.DEFAULT_RULES,
) -> StepFn:
    """The world model's step through the one compile helper, :func:`sword_jax.sharding.compile_step`:
    explicit in/out shardings (the train state's and the loader's), the state donated, activations
    constrained through :func:`sword_jax.sharding.use_mesh` while tracing."""
    return shd.compile_step(step_fn, mesh, rules, state_shardings=state_shardings, batch_shardings=batch_shardings)
