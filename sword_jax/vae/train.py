"""Training the VAE from scratch: train state, loss, and a jitted ``step(state, batch, key) -> (state, metrics)``.

Loss (float32): ``l1_weight * mean|x - x_hat| + l2_weight * mean (x - x_hat)^2 + kl_weight * KL +
perceptual_weight * perceptual_fn(x, x_hat)``, where ``x_hat`` decodes a reparameterised sample of
the raw posterior ``N(mu, exp(log_var))`` (the official encode only returns mu; the log_var
branch is trained here) and ``KL = mean 0.5 (mu^2 + exp(log_var) - 1 - log_var)`` per element.
Parameters are float32; convs run in ``cfg.compute_dtype``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jaxtyping import Array, Float

from sword_jax import optim, sharding, tracing
from sword_jax.vae.config import VAEConfig
from sword_jax.vae.layers import patchify, unpatchify
from sword_jax.vae.model import WanVAE, vae_rngs

PerceptualFn = Callable[[Float[Array, "b t h w 3"], Float[Array, "b t h w 3"]], Float[Array, ""]]
VIDEO_AXES = ("batch", "time", "height", "width", "channels")


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["params", "constants", "opt_state", "step"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class VAETrainState:
    """Everything a VAE training step updates.

    Attributes:
      params: ``nnx.Param`` state (float32).
      constants: the other variables (latent statistics), carried unchanged.
      opt_state: optax state.
      step: int32 scalar, number of steps taken.
    """

    params: nnx.State
    constants: nnx.State
    opt_state: optax.OptState
    step: jax.Array


def vae_optimizer(cfg: VAEConfig) -> optax.GradientTransformation:
    """AdamW (b2 0.99) at a constant rate with optional global-norm clipping."""
    return optim.make_optimizer(cfg.learning_rate, b1=0.9, b2=0.99, weight_decay=cfg.weight_decay,
                                grad_clip=cfg.grad_clip)


def init_train_state(
    cfg: VAEConfig, *, key: jax.Array, mesh: jax.sharding.Mesh | None = None,
    rules: Sequence[tuple[str, Sequence[str]]] = sharding.DEFAULT_RULES,
) -> tuple[nnx.GraphDef, VAETrainState]:
    """Fresh VAE parameters and optimizer state; born sharded over ``mesh`` when given."""
    cfg.validate()

    def factory():
        return WanVAE(cfg, rngs=vae_rngs(key))

    graphdef, state = sharding.create(factory, mesh, rules)
    params, constants = state.split(nnx.Param, ...)
    opt_state = jax.jit(vae_optimizer(cfg).init)(params)
    step = jnp.zeros((), jnp.int32)
    if mesh is not None:
        # Moments inherit the params' shardings; scalars (counts, step) are replicated over the mesh.
        def place(x):
            return x if len(x.sharding.device_set) == mesh.size else sharding.put(x, sharding.replicated(mesh))

        opt_state = jax.tree.map(place, opt_state)
        step = sharding.put(step, sharding.replicated(mesh))
    return graphdef, VAETrainState(params, constants, opt_state, step)


def moving_squares(*, key: jax.Array, batch: int, frames: int, size: int,
                   rows: np.ndarray | None = None) -> Float[Array, "r t h w 3"]:
    """Synthetic videos in [-1, 1]: a coloured square moving at constant velocity over a tinted background.

    The squares of all ``batch`` videos are drawn; only ``rows`` of them (default: all) are drawn out as
    pixels, so a row is the same whichever rows are asked for.
    """
    k_pos, k_vel, k_col, k_bg = jax.random.split(key, 4)
    side = max(size // 4, 2)
    start = jax.random.uniform(k_pos, (batch, 2), minval=0.0, maxval=float(size - side))
    velocity = jax.random.uniform(k_vel, (batch, 2), minval=-2.0, maxval=2.0)
    colour = jax.random.uniform(k_col, (batch, 1, 1, 1, 3), minval=-1.0, maxval=1.0)
    background = jax.random.uniform(k_bg, (batch, 1, 1, 1, 3), minval=-0.5, maxval=0.5)
    if rows is not None:
        start, velocity, colour, background = (x[np.asarray(rows)] for x in (start, velocity, colour, background))
    t = jnp.arange(frames, dtype=jnp.float32)
    corner = jnp.mod(start[:, None, :] + velocity[:, None, :] * t[None, :, None], float(size - side))  # (B, T, 2)
    grid = jnp.arange(size, dtype=jnp.float32)
    rows = (grid[None, None, :] >= corner[..., 0:1]) & (grid[None, None, :] < corner[..., 0:1] + side)
    cols = (grid[None, None, :] >= corner[..., 1:2]) & (grid[None, None, :] < corner[..., 1:2] + side)
    inside = (rows[..., :, None] & cols[..., None, :])[..., None]  # (B, T, H, W, 1)
    return jnp.where(inside, colour, background).astype(jnp.float32)


def loss_fn(
    params: nnx.State, constants: nnx.State, graphdef: nnx.GraphDef, video: Float[Array, "b t h w 3"], *,
    key: jax.Array, cfg: VAEConfig, perceptual_fn: PerceptualFn | None = None,
) -> tuple[Float[Array, ""], dict[str, Array]]:
    """Reconstruction + KL (+ perceptual) loss of one batch, float32."""
    model = nnx.merge(graphdef, params, constants)
    dtype = jnp.dtype(cfg.compute_dtype)
    video = sharding.constrain(video.astype(jnp.float32), VIDEO_AXES)
    mu, log_var, _ = model.encode_moments(patchify(video), None, first=True, dtype=dtype)
    log_var = jnp.clip(log_var, -30.0, 20.0)
    noise = jax.random.normal(key, mu.shape, jnp.float32)
    z = mu + jnp.exp(jnp.float32(0.5) * log_var) * noise
    out, _ = model.decode_raw(z, None, first=True, dtype=dtype)
    recon = unpatchify(out.astype(jnp.float32))
    err = recon - video
    l1 = jnp.mean(jnp.abs(err))
    l2 = jnp.mean(err * err)
    kl = jnp.mean(jnp.float32(0.5) * (mu * mu + jnp.exp(log_var) - jnp.float32(1.0) - log_var))
    loss = jnp.float32(cfg.l1_weight) * l1 + jnp.float32(cfg.l2_weight) * l2 + jnp.float32(cfg.kl_weight) * kl
    perceptual = jnp.zeros((), jnp.float32)
    if perceptual_fn is not None and cfg.perceptual_weight > 0:
        perceptual = perceptual_fn(video, recon).astype(jnp.float32)
        loss = loss + jnp.float32(cfg.perceptual_weight) * perceptual
    return loss, {"loss": loss, "l1": l1, "l2": l2, "kl": kl, "perceptual": perceptual}


def _tree_norm(tree) -> Array:
    return optax.global_norm(jax.tree.map(lambda x: x.astype(jnp.float32), tree))


def make_vae_step(
    graphdef: nnx.GraphDef, cfg: VAEConfig, *, state: VAETrainState | None = None,
    mesh: jax.sharding.Mesh | None = None, rules: Sequence[tuple[str, Sequence[str]]] = sharding.DEFAULT_RULES,
    perceptual_fn: PerceptualFn | None = None, max_traces: int = 1,
) -> Callable[[VAETrainState, dict[str, Array], jax.Array], tuple[VAETrainState, dict[str, Array]]]:
    """Builds ``step(state, batch, key) -> (state, metrics)``, jitted with the state donated.

    Args:
      graphdef: from :func:`init_train_state`.
      cfg: loss weights, optimizer and compute dtype.
      state: an example state; with ``mesh`` its shardings pin the step's in/out shardings.
      mesh: when given, ``batch["video"]`` is sharded over the ``batch`` logical axis (data/fsdp).
      rules: logical -> mesh axis table.
      perceptual_fn: optional ``(video, recon) -> scalar`` (e.g. LPIPS), weighted by ``perceptual_weight``.
      max_traces: bound on traces of this step (:func:`sword_jax.tracing.max_traces`).

    ``key`` is the run's root key; the step folds in ``state.step`` (exact resume).
    Metrics: loss, l1, l2, kl, perceptual, grad_norm, param_norm, update_norm (float32 scalars).
    """
    tx = vae_optimizer(cfg)

    @functools.partial(tracing.max_traces, n=max_traces)
    def step(state: VAETrainState, batch: dict[str, Array], key: jax.Array):
        step_key = jax.random.fold_in(key, state.step)
        grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
        (_, metrics), grads = grad_fn(
            state.params, state.constants, graphdef, batch["video"], key=step_key, cfg=cfg, perceptual_fn=perceptual_fn
        )
        updates, opt_state, params = optim.apply_optimizer(tx, grads, state.opt_state, state.params)
        metrics = dict(metrics, grad_norm=_tree_norm(grads), param_norm=_tree_norm(params),
                       update_norm=_tree_norm(updates))
        return VAETrainState(params, state.constants, opt_state, state.step + 1), metrics

    if mesh is None:
        return jax.jit(step, donate_argnums=(0,))
    if state is None:
        raise ValueError("make_vae_step: pass an example `state` together with `mesh` (its shardings are used)")
    state_sharding = jax.tree.map(lambda x: x.sharding, state)
    batch_sharding = {"video": sharding.batch_sharding(mesh, 5, rules)}
    replicated = sharding.replicated(mesh)
    jitted = jax.jit(step, in_shardings=(state_sharding, batch_sharding, replicated),
                     out_shardings=(state_sharding, replicated), donate_argnums=(0,))

    def sharded_step(state, batch, key):
        with sharding.use_mesh(mesh, rules):
            return jitted(state, batch, key)

    return sharded_step
