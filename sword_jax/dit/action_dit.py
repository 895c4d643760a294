"""The action-conditioned world model: Wan 2.2 TI2V DiT + dual action conditioning.

Actions (one per *video* frame, ``t = 1 + 4 (f - 1)`` for ``f`` latent frames) enter twice:

* **cross-attention tokens** (``cfg.action_cross_attn``): each action, together with a sinusoid
  of its video-frame index (cross-attention has no RoPE, so the order must be in the token), goes
  through an MLP to a ``dim``-wide token; the tokens replace the text embedding as the
  cross-attention context of every block. Switched off, a learned null token is attended instead.
* **AdaLN** (``cfg.action_adaln``): the chunk of actions behind each latent frame (4 actions; frame
  0 has one action, zero-padded in front to 4) goes through an MLP whose output is added to that
  frame's time embedding ``e``, so every block's modulation and the head see it. The MLP's last
  layer starts at zero, so a freshly loaded official model starts with the official modulation;
  its gradient is non-zero from the first step (it multiplies non-zero hidden activations).

The official ``text_embedding`` stays inside :class:`WanDiT` so official checkpoints load whole
(:func:`sword_jax.convert.wan22_dit.load_official_into_world_model`).
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from flax import nnx
from jaxtyping import Array, Float

from sword_jax.dit.config import FRAMES_PER_LATENT, DiTConfig
from sword_jax.dit.layers import check_shape, check_values, dtype_of, linear, timestep_sinusoid
from sword_jax.dit.model import WanDiT

ACTION_INDEX_DIM = 32  # width of the video-frame-index sinusoid fed with each action token
# fields an official checkpoint fixes (the rest are options: action switches, remat, dtypes)
ARCH_FIELDS = ("patch_size", "in_dim", "out_dim", "dim", "ffn_dim", "freq_dim", "num_heads", "num_layers",
               "text_dim", "text_len", "eps", "qk_norm", "cross_attn_norm")


def num_video_frames(latent_frames: int) -> int:
    """Video frames (= actions) behind ``latent_frames`` causal-VAE latent frames."""
    return 1 + FRAMES_PER_LATENT * (latent_frames - 1)


def action_chunks(actions: Float[Array, "b t a"]) -> Float[Array, "b f 4a"]:
    """Groups per-video-frame actions by latent frame: ``[0, 0, 0, a_0], [a_1..a_4], [a_5..a_8], ...``."""
    b, t, a = actions.shape
    padded = jnp.concatenate([jnp.zeros((b, FRAMES_PER_LATENT - 1, a), actions.dtype), actions], axis=1)
    return padded.reshape(b, (t + FRAMES_PER_LATENT - 1) // FRAMES_PER_LATENT, FRAMES_PER_LATENT * a)


class ActionConditioner(nnx.Module):
    """The two action branches: cross-attention tokens and the per-frame AdaLN offset."""

    def __init__(self, cfg: DiTConfig, *, rngs: nnx.Rngs):
        self.cfg = cfg
        cdt, pdt = dtype_of(cfg.compute_dtype), dtype_of(cfg.param_dtype)
        kw = dict(compute_dtype=cdt, param_dtype=pdt, rngs=rngs)
        with nnx.use_eager_sharding(False):
            if cfg.action_cross_attn:
                self.token_in = linear(cfg.action_dim + ACTION_INDEX_DIM, cfg.dim, ("action", "embed"), **kw)
                self.token_out = linear(cfg.dim, cfg.dim, ("mlp", "embed"), **kw)
                self.null_context = None
            else:
                self.token_in = self.token_out = None
                null = nnx.initializers.normal(1.0)(rngs.params(), (1, cfg.dim), pdt)
                self.null_context = nnx.Param(null, out_sharding=(None, "embed"))
            if cfg.action_adaln:
                self.chunk_in = linear(FRAMES_PER_LATENT * cfg.action_dim, cfg.dim, ("action", "embed"), **kw)
                self.chunk_out = linear(
                    cfg.dim, cfg.dim, ("mlp", "embed"), kernel_init=nnx.initializers.zeros_init(), **kw
                )
            else:
                self.chunk_in = self.chunk_out = None

    def context(self, actions: Float[Array, "b t a"]) -> Float[Array, "b lc d"]:
        """Cross-attention context: one token per action (or the learned null token)."""
        b, t, _ = actions.shape
        if self.token_in is None:
            return jnp.broadcast_to(self.null_context[...].astype(jnp.float32)[None], (b, 1, self.cfg.dim))
        index = timestep_sinusoid(jnp.arange(t, dtype=jnp.float32), ACTION_INDEX_DIM)
        features = jnp.concatenate([actions.astype(jnp.float32), jnp.broadcast_to(index, (b, t, ACTION_INDEX_DIM))], -1)
        hidden = jax.nn.gelu(self.token_in(features), approximate=True)
        return self.token_out(hidden).astype(jnp.float32)

    def time_offset(self, actions: Float[Array, "b t a"]) -> Float[Array, "b f d"] | None:
        """Per-latent-frame addition to the time embedding (None with ``action_adaln`` off)."""
        if self.chunk_in is None:
            return None
        hidden = jax.nn.silu(self.chunk_in(action_chunks(actions.astype(jnp.float32))))
        return self.chunk_out(hidden).astype(jnp.float32)


class ActionConditioning(NamedTuple):
    """What the world model reads of a segment's actions, computed once for calls that share them
    (:meth:`WorldModel.condition`): the sampler's Euler steps of one chunk all see the same actions.

    Attributes:
      context_kv: every block's cross-attention keys and values of the action tokens,
        ``[layers, b, lc, heads, dh]`` each (:meth:`~sword_jax.dit.model.WanDiT.cross_attention_kv`).
      time_offset: the AdaLN addition to each latent frame's time embedding ``[b, f, d]`` (None
        with ``action_adaln`` off).
    """

    context_kv: tuple[Array, Array]
    time_offset: Float[Array, "b f d"] | None


class WorldModel(nnx.Module):
    """:class:`WanDiT` conditioned on actions through cross-attention tokens and AdaLN."""

    def __init__(self, cfg: DiTConfig, *, rngs: nnx.Rngs):
        if cfg.patch_size[0] != 1:
            raise ValueError(f"model.patch_size: the world model needs temporal patch 1, got {cfg.patch_size}")
        self.cfg = cfg
        self.dit = WanDiT(cfg, rngs=rngs)
        self.actions = ActionConditioner(cfg, rngs=rngs)

    def __call__(
        self,
        latents: Float[Array, "b f h w c"],
        timesteps: Float[Array, "b f"],
        actions: Float[Array, "b t a"],
    ) -> Float[Array, "b f h w c"]:
        """Predicts the flow target of every latent frame.

        Args:
          latents: ``[first-frame latent, context latent, future latents...]``, channels-last,
            ``c = in_dim``; ``h, w`` divisible by the spatial patch.
          timesteps: Wan units [0, 1000], one per latent frame (0 for clean conditioning frames).
          actions: one ``action_dim`` action per video frame, ``t = 1 + 4 (f - 1)``.

        Returns:
          The raw prediction per latent frame, ``[b, f, h, w, out_dim]`` float32.
        """
        cfg = self.cfg
        b, f, h, w, _ = latents.shape
        check_shape("latents", latents, (None, None, None, None, cfg.in_dim))
        check_shape("timesteps", timesteps, (b, f))
        check_shape("actions", actions, (b, num_video_frames(f), cfg.action_dim))
        check_values("latents", latents)
        check_values("timesteps", timesteps, 0.0, 1000.0)
        check_values("actions", actions)
        return self._forward(latents, timesteps, self.actions.time_offset(actions),
                             context_emb=self.actions.context(actions))

    def condition(self, actions: Float[Array, "b t a"]) -> ActionConditioning:
        """The action branches' outputs for ``actions`` (one per video frame), to reuse across
        :meth:`apply_conditioned` calls: the same predictions as :meth:`__call__` with these actions."""
        check_shape("actions", actions, (None, None, self.cfg.action_dim))
        check_values("actions", actions)
        return ActionConditioning(self.dit.cross_attention_kv(self.actions.context(actions)),
                                  self.actions.time_offset(actions))

    def apply_conditioned(
        self,
        latents: Float[Array, "b f h w c"],
        timesteps: Float[Array, "b f"],
        conditioning: ActionConditioning,
    ) -> Float[Array, "b f h w c"]:
        """:meth:`__call__` with the actions' work already done (:meth:`condition`)."""
        b, f = latents.shape[:2]
        check_shape("latents", latents, (None, None, None, None, self.cfg.in_dim))
        check_shape("timesteps", timesteps, (b, f))
        if conditioning.time_offset is not None:
            check_shape("conditioning.time_offset", conditioning.time_offset, (b, f, self.cfg.dim))
        check_values("latents", latents)
        check_values("timesteps", timesteps, 0.0, 1000.0)
        return self._forward(latents, timesteps, conditioning.time_offset, context_kv=conditioning.context_kv)

    def _forward(self, latents, timesteps, time_offset, *, context_emb=None, context_kv=None):
        cfg, dit = self.cfg, self.dit
        b, f, h, w, _ = latents.shape
        grid = (f, h // cfg.patch_size[1], w // cfg.patch_size[2])
        time_emb = dit.embed_time(timesteps)  # (B, F, D)
        if time_offset is not None:
            time_emb = time_emb + time_offset
        out = dit.forward_tokens(dit.patchify(latents), dit.grid_positions(b, grid), time_emb, context_emb,
                                 context_kv=context_kv)
        return dit.unpatchify(out, grid)


def world_model_apply(
    graphdef: nnx.GraphDef,
    state: nnx.State,
    latents: Float[Array, "b f h w c"],
    timesteps: Float[Array, "b f"],
    actions: Float[Array, "b t a"],
) -> Float[Array, "b f h w c"]:
    """Functional form of :meth:`WorldModel.__call__` for use inside jitted steps."""
    return nnx.merge(graphdef, state)(latents, timesteps, actions)


def replace_options(cfg: DiTConfig, **options: Any) -> DiTConfig:
    """Copy of ``cfg`` with non-architectural options changed (e.g. for ablations)."""
    bad = set(options) & set(ARCH_FIELDS)
    if bad:
        raise ValueError(f"replace_options: {sorted(bad)} change the architecture")
    return dataclasses.replace(cfg, **options)
