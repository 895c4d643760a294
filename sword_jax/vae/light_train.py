"""Distilling the light decoder (:mod:`sword_jax.vae.light_decoder`) from the VAE's decoder.

The teacher decodes a clip of latents at the VAE's resolution; its frames, clipped to [-1, 1] and
resized to the light decoder's resolution as the policy resizes frames (linear, antialiased), are the
target. Loss (float32): ``l1_weight * mean|y - t| + l2_weight * mean (y - t)^2 + perceptual_weight *
perceptual_fn(t, y)``. The teacher runs inside the step (its weights a jit argument, never trained or
checkpointed); ``step(state, batch, key)`` is the shared loop's signature once the teacher is bound
(:func:`bind_teacher`).

Clips (:class:`ClipSampler`): the episode's first latent, then ``clip_latents`` consecutive latents from
a random position, the layout the learned simulator decodes (start latent, context, predictions). A
batch is a pure function of the step, so the train state alone makes an exact resume. In a job of several
processes each one cuts only the rows of a batch its devices hold (:func:`clip_loader`); every draw is made for
the whole batch, so a row is the same whichever process cuts it.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jaxtyping import Array, Float

from sword_jax import optim, sharding, tracing
from sword_jax.rng import stream_rng
from sword_jax.vae import api as vae_api
from sword_jax.vae import light_decoder as light
from sword_jax.vae.config import LightDecoderConfig
from sword_jax.vae.model import vae_rngs

PerceptualFn = Callable[[Float[Array, "b t h w 3"], Float[Array, "b t h w 3"]], Float[Array, ""]]
LATENT_AXES = ("batch", "time", "height", "width", "channels")


@functools.partial(jax.tree_util.register_dataclass, data_fields=["params", "opt_state", "step"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class LightTrainState:
    """Everything a distillation step updates: the light decoder's params (float32, a pure dict), the optax state
    and the int32 step count."""

    params: dict
    opt_state: optax.OptState
    step: jax.Array


def light_optimizer(cfg: LightDecoderConfig) -> optax.GradientTransformation:
    """AdamW (b2 0.99) at a constant rate with optional global-norm clipping."""
    return optim.make_optimizer(cfg.learning_rate, b1=0.9, b2=0.99, weight_decay=cfg.weight_decay,
                                grad_clip=cfg.grad_clip)


def init_train_state(
    cfg: LightDecoderConfig, *, z_dim: int, scale: int, temporal_factor: int, key: jax.Array,
    mesh: jax.sharding.Mesh | None = None, rules: Sequence[tuple[str, Sequence[str]]] = sharding.DEFAULT_RULES,
) -> tuple[nnx.GraphDef, LightTrainState]:
    """Fresh light-decoder parameters and optimizer state; born sharded over ``mesh`` when given."""
    def factory():
        return light.LightDecoder(cfg, z_dim=z_dim, scale=scale, temporal_factor=temporal_factor, rngs=vae_rngs(key))

    graphdef, params = sharding.create(factory, mesh, rules)
    params = nnx.to_pure_dict(params)  # plain nested dicts of arrays: what a checkpoint's "params" holds
    opt_state = jax.jit(light_optimizer(cfg).init)(params)
    step = jnp.zeros((), jnp.int32)
    if mesh is not None:  # moments keep the params' shardings; scalars are replicated over the mesh
        opt_state = sharding.place(opt_state, sharding.shardings_on(opt_state, mesh))
        step = sharding.put(step, sharding.replicated(mesh))
    return graphdef, LightTrainState(params, opt_state, step)


def resize_video(video: Float[Array, "b t h w 3"], size: int) -> Float[Array, "b t s s 3"]:
    """Frames resized to ``size x size`` as the policy resizes them (linear, antialiased); a no-op at that size."""
    if video.shape[2:4] == (size, size):
        return video
    return jax.image.resize(video, video.shape[:2] + (size, size, video.shape[-1]), method="linear", antialias=True)


def teacher_frames(teacher_graphdef: nnx.GraphDef, teacher_state: Any, latents: Float[Array, "b tl hl wl z"], *,
                   frame_size: int) -> Float[Array, "b t s s 3"]:
    """The VAE's decode of ``latents``, clipped to [-1, 1] (as the simulator's frames are) and resized to
    ``frame_size``: the light decoder's target (float32, no gradient)."""
    video = vae_api.decode(teacher_graphdef, teacher_state, latents, clamp=True, check_values=False)
    return jax.lax.stop_gradient(resize_video(video.astype(jnp.float32), frame_size))


def frame_psnr(pred: Float[Array, "..."], target: Float[Array, "..."]) -> Float[Array, ""]:
    """PSNR in dB of [-1, 1] frames as the simulator shows them (clipped to [0, 1])."""
    unit = lambda v: jnp.clip((v.astype(jnp.float32) + 1.0) * jnp.float32(0.5), 0.0, 1.0)  # noqa: E731
    mse = jnp.mean(jnp.square(unit(pred) - unit(target)))
    return jnp.float32(-10.0) * jnp.log10(jnp.maximum(mse, jnp.float32(1e-10)))


def loss_fn(params: nnx.State, graphdef: nnx.GraphDef, latents: Float[Array, "b tl hl wl z"],
            target: Float[Array, "b t s s 3"], *, cfg: LightDecoderConfig,
            perceptual_fn: PerceptualFn | None = None) -> tuple[Float[Array, ""], dict[str, Array]]:
    """The light decoder's loss against the teacher's frames ``target``, float32."""
    video = light.decode(graphdef, params, latents, compute_dtype=cfg.compute_dtype)
    err = video - target
    l1, l2 = jnp.mean(jnp.abs(err)), jnp.mean(err * err)
    loss = jnp.float32(cfg.l1_weight) * l1 + jnp.float32(cfg.l2_weight) * l2
    perceptual = jnp.zeros((), jnp.float32)
    if perceptual_fn is not None and cfg.perceptual_weight > 0:
        perceptual = perceptual_fn(target, video).astype(jnp.float32)
        loss = loss + jnp.float32(cfg.perceptual_weight) * perceptual
    return loss, {"loss": loss, "l1": l1, "l2": l2, "perceptual": perceptual,
                  "psnr": frame_psnr(jax.lax.stop_gradient(video), target)}


def _tree_norm(tree) -> Array:
    return optax.global_norm(jax.tree.map(lambda x: x.astype(jnp.float32), tree))


def make_distill_step(
    graphdef: nnx.GraphDef, teacher_graphdef: nnx.GraphDef, cfg: LightDecoderConfig, *, frame_size: int,
    perceptual_fn: PerceptualFn | None = None,
) -> Callable[[Any, LightTrainState, dict[str, Array], jax.Array], tuple[LightTrainState, dict[str, Array]]]:
    """The pure ``step(teacher_state, state, batch, key) -> (state, metrics)`` (``batch["latents"]``:
    ``[B, 1 + clip_latents, h, w, z]``); :func:`bind_teacher` compiles it to the loop's signature.

    ``key`` is the run's root key; the step folds in ``state.step`` (exact resume) and draws the latent
    noise from it. Metrics: loss, l1, l2, perceptual, psnr (dB, student vs teacher), grad_norm, param_norm,
    update_norm (float32 scalars).
    """
    tx = light_optimizer(cfg)

    def step(teacher_state, state: LightTrainState, batch: dict[str, Array], key: jax.Array):
        step_key = jax.random.fold_in(key, state.step)
        latents = sharding.constrain(batch["latents"].astype(jnp.float32), LATENT_AXES)
        if cfg.latent_noise > 0:
            noise_key = jax.random.fold_in(step_key, 0)
            latents = latents + jnp.float32(cfg.latent_noise) * jax.random.normal(noise_key, latents.shape, jnp.float32)
        target = teacher_frames(teacher_graphdef, teacher_state, latents, frame_size=frame_size)
        (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params, graphdef, latents, target, cfg=cfg, perceptual_fn=perceptual_fn)
        updates, opt_state, params = optim.apply_optimizer(tx, grads, state.opt_state, state.params)
        metrics = dict(metrics, grad_norm=_tree_norm(grads), param_norm=_tree_norm(params),
                       update_norm=_tree_norm(updates))
        return LightTrainState(params, opt_state, state.step + 1), metrics

    return step


def bind_teacher(step: Callable, teacher_state: Any, state: LightTrainState, batch_example: dict[str, Any], *,
                 mesh: jax.sharding.Mesh, rules: Sequence[tuple[str, Sequence[str]]] = sharding.DEFAULT_RULES,
                 max_traces: int = 1) -> Callable[[LightTrainState, dict[str, Array], jax.Array], tuple]:
    """``step(state, batch, key)``: :func:`make_distill_step`'s step jitted once with explicit shardings (the
    state's own, the batch's leading axis over ``batch``, the teacher's weights as they lie on ``mesh``), the
    state donated and the teacher's weights passed as an argument (not baked into the program)."""
    state_shardings = sharding.shardings_on(state, mesh)
    teacher_shardings = sharding.shardings_on(teacher_state, mesh)
    batch_shardings = sharding.leading_axis_shardings(batch_example, mesh, rules)
    replicated = sharding.replicated(mesh)
    jitted = jax.jit(tracing.max_traces(step, n=max_traces),
                     in_shardings=(teacher_shardings, state_shardings, batch_shardings, replicated),
                     out_shardings=(state_shardings, replicated), donate_argnums=(1,))

    def bound(state, batch, key):
        with sharding.use_mesh(mesh, rules):
            return jitted(teacher_state, state, batch, key)

    return bound


def cut_clip(latents: np.ndarray, episode: int, start: int, clip_latents: int) -> np.ndarray:
    """Episode ``episode``'s first latent, then its ``clip_latents`` latents from ``start``:
    ``[1 + clip_latents, h, w, z]``."""
    return np.concatenate([latents[episode, :1], latents[episode, start:start + clip_latents]])


class ClipSampler:
    """Training clips of a latent dataset ``[E, L, h, w, z]``, each a pure function of (seed, step).

    A clip is the episode's first latent followed by ``clip_latents`` consecutive latents starting at a
    uniformly drawn position ``>= 1``: ``[batch, 1 + clip_latents, h, w, z]``.
    """

    def __init__(self, latents: np.ndarray, *, batch: int, clip_latents: int, seed: int,
                 name: str = "light_decoder/clips"):
        if latents.ndim != 5:
            raise ValueError(f"light decoder clips: latents must be [E, L, h, w, z], got shape {latents.shape}")
        if latents.shape[1] < clip_latents + 1:
            raise ValueError(f"light decoder clips: episodes of {latents.shape[1]} latents cannot hold the first "
                             f"latent and {clip_latents} more (light_decoder.clip_latents)")
        self.latents, self.batch, self.clip_latents, self.seed, self.name = latents, batch, clip_latents, seed, name

    def batch_at(self, step: int, rows: np.ndarray | None = None) -> np.ndarray:
        """Rows ``rows`` (default: all) of step ``step``'s clips, ``[R, 1 + clip_latents, h, w, z]`` float32.

        The episode and start of all ``batch`` clips are drawn; only ``rows`` of them are cut.
        """
        rng = stream_rng(self.seed, self.name, step)
        episodes = rng.integers(0, self.latents.shape[0], self.batch)
        starts = rng.integers(1, self.latents.shape[1] - self.clip_latents + 1, self.batch)
        if rows is not None:
            episodes, starts = episodes[rows], starts[rows]
        clips = [cut_clip(self.latents, e, s, self.clip_latents) for e, s in zip(episodes, starts)]
        return np.stack(clips).astype(np.float32)


def clip_loader(sampler: ClipSampler, mesh: jax.sharding.Mesh,
                rules: Sequence[tuple[str, Sequence[str]]] = sharding.DEFAULT_RULES, *,
                devices: Sequence[jax.Device] | None = None) -> sharding.RowLoader:
    """``sampler``'s batches ``{"latents": [B, 1 + clip_latents, h, w, z]}`` (the step's input), each process
    cutting only the rows its devices (or ``devices``) hold.

    Raises:
      ValueError: ``sampler.batch`` does not split evenly over the devices the rows are sharded over
        (naming ``light_decoder.batch_size``, the devices and the mesh).
    """
    return sharding.RowLoader(sampler.batch_at, sampler.batch, mesh, rules, field="latents", ndim=5,
                              name="light_decoder.batch_size", devices=devices)
