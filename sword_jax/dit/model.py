"""The Wan 2.2 TI2V diffusion transformer (``WanModel``) in Flax NNX, channels-last.

Parity target: the official PyTorch ``WanModel`` (TI2V-5B layout). Blocks are created stacked
(leading ``layers`` axis, ``nnx.vmap`` + ``nnx.split_rngs``) and run with ``jax.lax.scan`` (or a
Python loop over the same stacked parameters when ``cfg.scan_layers`` is False), optionally
rematerialised. The residual stream, norms, modulation and RoPE run in float32; linear layers and
attention run in ``cfg.compute_dtype``.

Timestep conditioning is per *group* of tokens: the time embedding ``e`` has shape
``[b, g, dim]`` and each of the ``g`` groups owns ``l / g`` consecutive tokens. The world model
uses one group per latent frame; the official per-token rule is ``g = l``.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx
from jax.ad_checkpoint import checkpoint_name
from jaxtyping import Array, Float, Int

from sword_jax import sharding
from sword_jax.dit.config import DiTConfig
from sword_jax.dit.layers import (
    AffineLayerNorm,
    RMSNorm,
    apply_rope,
    attention,
    check_shape,
    dtype_of,
    layer_norm,
    linear,
    matmul_precision,
    rope_cos_sin,
    timestep_sinusoid,
)

TOKENS = ("batch", "length", "embed")


class WanAttention(nnx.Module):
    """Multi-head attention with q/k RMSNorm over the full width (self- or cross-attention)."""

    def __init__(self, cfg: DiTConfig, *, rngs: nnx.Rngs):
        cdt, pdt = dtype_of(cfg.compute_dtype), dtype_of(cfg.param_dtype)
        kw = dict(compute_dtype=cdt, param_dtype=pdt, rngs=rngs)
        self.num_heads = cfg.num_heads
        self.impl = cfg.attention_impl
        self.q = linear(cfg.dim, cfg.dim, ("embed", "heads"), **kw)
        self.k = linear(cfg.dim, cfg.dim, ("embed", "heads"), **kw)
        self.v = linear(cfg.dim, cfg.dim, ("embed", "heads"), **kw)
        self.o = linear(cfg.dim, cfg.dim, ("heads", "embed"), **kw)
        self.norm_q = RMSNorm(cfg.dim, cfg.eps, "heads", param_dtype=pdt) if cfg.qk_norm else None
        self.norm_k = RMSNorm(cfg.dim, cfg.eps, "heads", param_dtype=pdt) if cfg.qk_norm else None

    def project_kv(self, source: Float[Array, "b ls d"]) -> tuple[Float[Array, "b ls n dh"], Float[Array, "b ls n dh"]]:
        """Keys (q/k-normed) and values of ``source``, split into heads: what cross-attention reads of its
        context, so a context fixed over several calls is projected once (:meth:`WanDiT.cross_attention_kv`)."""
        b, ls, d = source.shape
        k, v = self.k(source), self.v(source)
        if self.norm_k is not None:
            k = self.norm_k(k)
        heads = self.num_heads
        return k.reshape(b, ls, heads, d // heads), v.reshape(b, ls, heads, d // heads)  # (B, Ls, N, Dh)

    def __call__(
        self,
        x: Float[Array, "b l d"],
        context: Float[Array, "b lc d"] | None = None,
        *,
        rope: tuple[Array, Array] | None = None,
        key_lengths: Int[Array, " b"] | None = None,
        context_kv: tuple[Array, Array] | None = None,
    ) -> tuple[Float[Array, "b l d"], dict[str, Array]]:
        """Self-attention when ``context`` and ``context_kv`` are None (with RoPE and key masking), else
        cross-attention to ``context``, or to its keys and values already projected (:meth:`project_kv`)."""
        b, l, d = x.shape
        heads = self.num_heads
        q = self.q(x)
        if self.norm_q is not None:
            q = self.norm_q(q)
        q = q.reshape(b, l, heads, d // heads)  # (B, L, N, Dh)
        k, v = context_kv if context_kv is not None else self.project_kv(x if context is None else context)
        if rope is not None:
            q, k = apply_rope(q, *rope), apply_rope(k, *rope)
        out = checkpoint_name(attention(q, k, v, key_lengths=key_lengths, impl=self.impl), "attention_out")
        aux = {"q_roped": q, "k_roped": k, "v": v, "attn": out}
        return self.o(out.reshape(b, l, d)), aux


class WanBlock(nnx.Module):
    """``WanAttentionBlock``: modulated self-attention, cross-attention (norm3), modulated FFN."""

    def __init__(self, cfg: DiTConfig, *, rngs: nnx.Rngs):
        cdt, pdt = dtype_of(cfg.compute_dtype), dtype_of(cfg.param_dtype)
        kw = dict(compute_dtype=cdt, param_dtype=pdt, rngs=rngs)
        self.eps = cfg.eps
        self.compute_dtype = cdt
        self.residual_dtype = dtype_of(cfg.residual_dtype)
        self.self_attn = WanAttention(cfg, rngs=rngs)
        self.cross_attn = WanAttention(cfg, rngs=rngs)
        self.norm3 = AffineLayerNorm(cfg.dim, cfg.eps, param_dtype=pdt) if cfg.cross_attn_norm else None
        self.ffn_0 = linear(cfg.dim, cfg.ffn_dim, ("embed", "mlp"), **kw)
        self.ffn_2 = linear(cfg.ffn_dim, cfg.dim, ("mlp", "embed"), **kw)
        init = nnx.initializers.normal(1.0 / math.sqrt(cfg.dim))
        self.modulation = nnx.Param(init(rngs.params(), (6, cfg.dim), pdt), out_sharding=("modulation", "embed"))

    def __call__(
        self,
        x: Float[Array, "b l d"],
        e0: Float[Array, "b g 6 d"],
        context: Float[Array, "b lc d"] | None,
        rope: tuple[Array, Array],
        key_lengths: Int[Array, " b"] | None,
        context_kv: tuple[Array, Array] | None = None,
    ) -> tuple[Float[Array, "b l d"], dict[str, Array]]:
        """``context_kv``: this block's cross-attention keys and values of ``context``, projected once for
        calls that share it (``context`` is then not read)."""
        b, l, d = x.shape
        groups = e0.shape[1]
        x = x.astype(jnp.float32)  # the stream arrives in cfg.residual_dtype; the block adds in float32
        mod = self.modulation[...].astype(jnp.float32) + e0  # (B, G, 6, D)
        mod = mod[:, :, None]  # (B, G, 1, 6, D): broadcast over each group's tokens
        shift_sa, scale_sa, gate_sa, shift_ff, scale_ff, gate_ff = (mod[..., i, :] for i in range(6))

        def grouped(t):  # (B, L, D) -> (B, G, L/G, D)
            return t.reshape(b, groups, l // groups, d)

        cdt = self.compute_dtype
        h = grouped(layer_norm(x, self.eps)) * (1 + scale_sa) + shift_sa
        h = checkpoint_name(h.reshape(b, l, d).astype(cdt), "modulated_in")
        sa_out, aux = self.self_attn(h, rope=rope, key_lengths=key_lengths)
        x = x + (grouped(sa_out.astype(jnp.float32)) * gate_sa).reshape(b, l, d)

        normed = self.norm3(x) if self.norm3 is not None else x
        if context_kv is None:
            ca_out, _ = self.cross_attn(normed.astype(cdt), context.astype(cdt))
        else:
            ca_out, _ = self.cross_attn(normed.astype(cdt), context_kv=context_kv)
        x = x + ca_out.astype(jnp.float32)

        h = grouped(layer_norm(x, self.eps)) * (1 + scale_ff) + shift_ff
        h = checkpoint_name(h.reshape(b, l, d).astype(cdt), "modulated_in")
        hidden = checkpoint_name(jax.nn.gelu(self.ffn_0(h), approximate=True), "ffn_hidden")
        ffn_out = self.ffn_2(hidden)
        x = x + (grouped(ffn_out.astype(jnp.float32)) * gate_ff).reshape(b, l, d)
        aux = {f"sa_{k}": v for k, v in aux.items()}
        aux.update(self_attn_out=sa_out, cross_attn_out=ca_out, ffn_out=ffn_out)
        return x.astype(self.residual_dtype), aux


def _remat_policy(name: str):
    """``dots``: keep matmul outputs, recompute the rest. ``dots_acts``: also keep the bf16
    matmul inputs that are costly to recompute (the modulated norms, the attention output -- which
    otherwise reruns the attention kernel -- and the FFN's GELU output)."""
    policies = jax.checkpoint_policies
    if name == "dots":
        return policies.dots_with_no_batch_dims_saveable
    if name == "dots_acts":
        return policies.save_from_both_policies(
            policies.dots_with_no_batch_dims_saveable,
            policies.save_only_these_names("modulated_in", "attention_out", "ffn_hidden"))
    return policies.nothing_saveable


class WanDiT(nnx.Module):
    """Wan 2.2 TI2V ``WanModel``.

    Attribute names map one-to-one onto the official state dict (see
    :mod:`sword_jax.convert.wan22_dit`). Parameters are float32 (``cfg.param_dtype``).
    """

    def __init__(self, cfg: DiTConfig, *, rngs: nnx.Rngs):
        cfg.validate()
        self.cfg = cfg
        cdt, pdt = dtype_of(cfg.compute_dtype), dtype_of(cfg.param_dtype)
        kw = dict(compute_dtype=cdt, param_dtype=pdt, rngs=rngs)
        embed_init = nnx.initializers.normal(0.02)
        with nnx.use_eager_sharding(False):
            patch_features = math.prod(cfg.patch_size) * cfg.in_dim
            # Conv3d with kernel = stride = patch, kept in channels-last conv layout (pt, ph, pw, c_in, dim).
            kernel = nnx.initializers.xavier_uniform()(rngs.params(), (patch_features, cfg.dim), pdt)
            self.patch_kernel = nnx.Param(
                kernel.reshape(*cfg.patch_size, cfg.in_dim, cfg.dim), out_sharding=(None, None, None, "channels", "embed")
            )
            self.patch_bias = nnx.Param(jnp.zeros((cfg.dim,), pdt), out_sharding=("embed",))
            self.text_embedding_0 = linear(cfg.text_dim, cfg.dim, (None, "embed"), kernel_init=embed_init, **kw)
            self.text_embedding_2 = linear(cfg.dim, cfg.dim, ("mlp", "embed"), kernel_init=embed_init, **kw)
            self.time_embedding_0 = linear(cfg.freq_dim, cfg.dim, (None, "embed"), kernel_init=embed_init, **kw)
            self.time_embedding_2 = linear(cfg.dim, cfg.dim, ("mlp", "embed"), kernel_init=embed_init, **kw)
            self.time_projection = linear(cfg.dim, 6 * cfg.dim, ("embed", "mlp"), **kw)

            @nnx.split_rngs(splits=cfg.num_layers)
            @nnx.vmap(in_axes=(0,), out_axes=0, transform_metadata={nnx.PARTITION_NAME: "layers"})
            def make_blocks(block_rngs: nnx.Rngs) -> WanBlock:
                return WanBlock(cfg, rngs=block_rngs)

            self.blocks = make_blocks(rngs)
            out_features = math.prod(cfg.patch_size) * cfg.out_dim
            self.head = linear(cfg.dim, out_features, ("embed", None), kernel_init=nnx.initializers.zeros_init(), **kw)
            head_mod = nnx.initializers.normal(1.0 / math.sqrt(cfg.dim))(rngs.params(), (2, cfg.dim), pdt)
            self.head_modulation = nnx.Param(head_mod, out_sharding=("modulation", "embed"))

    # ----------------------------------------------------------------------------------------- embeddings

    def embed_time(self, t: Float[Array, "b g"]) -> Float[Array, "b g d"]:
        """Sinusoid (float64-accurate) -> Linear, SiLU, Linear: the time embedding ``e`` (float32)."""
        sinusoid = timestep_sinusoid(t, self.cfg.freq_dim)
        hidden = jax.nn.silu(self.time_embedding_0(sinusoid).astype(jnp.float32))
        return self.time_embedding_2(hidden).astype(jnp.float32)

    def embed_text(self, context: Float[Array, "b lc text_dim"]) -> Float[Array, "b text_len d"]:
        """Zero-pads the context to ``text_len`` rows (no mask, as the official model), then the MLP."""
        cfg = self.cfg
        check_shape("context", context, (None, None, cfg.text_dim))
        if context.shape[1] > cfg.text_len:
            raise ValueError(f"context: {context.shape[1]} rows exceed text_len={cfg.text_len}")
        context = jnp.pad(context, ((0, 0), (0, cfg.text_len - context.shape[1]), (0, 0)))
        hidden = jax.nn.gelu(self.text_embedding_0(context), approximate=True)
        return self.text_embedding_2(hidden).astype(jnp.float32)

    # ------------------------------------------------------------------------------------------ tokens

    def patchify(self, latents: Float[Array, "b f h w c"]) -> Float[Array, "b l p"]:
        """Cuts ``(pt, ph, pw)`` patches; tokens in (f, h, w) row-major order, features (pt, ph, pw, c)."""
        pt, ph, pw = self.cfg.patch_size
        b, f, h, w, c = latents.shape
        if f % pt or h % ph or w % pw:
            raise ValueError(f"latents: (f, h, w) = {(f, h, w)} not divisible by patch_size {self.cfg.patch_size}")
        x = latents.reshape(b, f // pt, pt, h // ph, ph, w // pw, pw, c)
        x = x.transpose(0, 1, 3, 5, 2, 4, 6, 7)  # (B, F', H', W', pt, ph, pw, C)
        return x.reshape(b, (f // pt) * (h // ph) * (w // pw), pt * ph * pw * c)

    def unpatchify(self, tokens: Float[Array, "b l p"], grid: tuple[int, int, int]) -> Float[Array, "b f h w c"]:
        """Inverse of :meth:`patchify` for ``out_dim`` channels; uses the first ``prod(grid)`` tokens."""
        pt, ph, pw = self.cfg.patch_size
        f, h, w = grid
        b = tokens.shape[0]
        x = tokens[:, : f * h * w].reshape(b, f, h, w, pt, ph, pw, self.cfg.out_dim)
        x = x.transpose(0, 1, 4, 2, 5, 3, 6, 7)  # (B, F', pt, H', ph, W', pw, C)
        return x.reshape(b, f * pt, h * ph, w * pw, self.cfg.out_dim)

    @staticmethod
    def grid_positions(batch: int, grid: tuple[int, int, int]) -> Int[Array, "b l 3"]:
        """Integer (frame, height, width) index of every token of a ``grid``, row-major."""
        f, h, w = grid
        mesh = jnp.stack(jnp.meshgrid(jnp.arange(f), jnp.arange(h), jnp.arange(w), indexing="ij"), axis=-1)
        return jnp.broadcast_to(mesh.reshape(1, f * h * w, 3), (batch, f * h * w, 3)).astype(jnp.int32)

    # ------------------------------------------------------------------------------------------ forward

    def forward_tokens(
        self,
        patches: Float[Array, "b l p"],
        positions: Int[Array, "b l 3"],
        time_emb: Float[Array, "b g d"],
        context_emb: Float[Array, "b lc d"] | None,
        seq_lens: Int[Array, " b"] | None = None,
        *,
        capture: bool = False,
        context_kv: tuple[Array, Array] | None = None,
    ) -> Float[Array, "b l q"] | tuple[Float[Array, "b l q"], dict[str, Array]]:
        """The transformer on patch tokens: patch embed, blocks, modulated head (before unpatchify).

        Args:
          patches: patchified latents (:meth:`patchify`), zero rows for padding.
          positions: (f, h, w) grid index per token, for RoPE.
          time_emb: time embedding ``e`` per token group; ``l % g == 0``.
          context_emb: cross-attention context, already at width ``dim``.
          seq_lens: valid tokens per sample (keys beyond are masked, their RoPE is identity);
            None = all valid.
          capture: also return a dict of intermediates (names as in the reference npz files).
          context_kv: every block's cross-attention keys and values of the context
            (:meth:`cross_attention_kv`), for calls that share one context; ``context_emb`` is then
            not read (pass None).

        Returns:
          Head output ``[b, l, prod(patch) * out_dim]`` in float32 (and the intermediates).
        """
        cfg = self.cfg
        b, l, _ = patches.shape
        check_shape("patches", patches, (None, None, math.prod(cfg.patch_size) * cfg.in_dim))
        check_shape("positions", positions, (b, l, 3))
        check_shape("time_emb", time_emb, (b, None, cfg.dim))
        if context_kv is None:
            check_shape("context_emb", context_emb, (b, None, cfg.dim))
        else:
            check_shape("context_kv keys", context_kv[0], (cfg.num_layers, b, None, cfg.num_heads, None))
        if l % time_emb.shape[1]:
            raise ValueError(f"time_emb: {time_emb.shape[1]} groups do not divide {l} tokens")
        cdt = dtype_of(cfg.compute_dtype)

        kernel = self.patch_kernel[...].reshape(-1, cfg.dim).astype(cdt)
        x = jnp.einsum("blp,pd->bld", patches.astype(cdt), kernel, precision=matmul_precision(cdt))
        x = x.astype(jnp.float32) + self.patch_bias[...].astype(jnp.float32)
        valid = None
        if seq_lens is not None:
            valid = (jnp.arange(l)[None, :] < seq_lens[:, None]).astype(jnp.float32)
            x = x * valid[..., None]  # padding rows start as zeros
        x = sharding.constrain(x, TOKENS)
        rope = rope_cos_sin(positions, cfg.dim // cfg.num_heads, valid)
        e0 = self.time_projection(jax.nn.silu(time_emb)).astype(jnp.float32)
        e0 = e0.reshape(b, time_emb.shape[1], 6, cfg.dim)
        context = None if context_kv is not None else context_emb.astype(cdt)
        intermediates: dict[str, Array] = {"tokens_in": x, "time_proj": e0} if capture else {}

        x, block_aux = self._run_blocks(x, e0, context, rope, seq_lens, capture, context_kv)
        if capture:
            intermediates.update(block_aux)

        head_mod = self.head_modulation[...].astype(jnp.float32)[None, None] + time_emb[:, :, None]  # (B, G, 2, D)
        groups = time_emb.shape[1]
        h = layer_norm(x, cfg.eps).reshape(b, groups, l // groups, cfg.dim)
        h = h * (1 + head_mod[:, :, None, 1]) + head_mod[:, :, None, 0]
        out = self.head(h.reshape(b, l, cfg.dim).astype(cdt)).astype(jnp.float32)
        if capture:
            intermediates["head_out"] = out
            return out, intermediates
        return out

    def cross_attention_kv(self, context_emb: Float[Array, "b lc d"]) -> tuple[Array, Array]:
        """Every block's cross-attention keys and values of ``context_emb``, ``[layers, b, lc, heads, dh]``
        each in the compute dtype: computed once, they serve every :meth:`forward_tokens` call with the
        same context (``context_kv=``), e.g. all sampler steps of one world-model chunk."""
        check_shape("context_emb", context_emb, (None, None, self.cfg.dim))
        context = context_emb.astype(dtype_of(self.cfg.compute_dtype))
        graphdef, block_state = nnx.split(self.blocks)
        return jax.vmap(lambda params: nnx.merge(graphdef, params).cross_attn.project_kv(context))(block_state)

    def _run_blocks(self, x, e0, context, rope, seq_lens, capture: bool, context_kv=None):
        cfg = self.cfg
        graphdef, block_state = nnx.split(self.blocks)
        x = x.astype(dtype_of(cfg.residual_dtype))

        def body(carry, xs):
            params, layer_kv = xs
            block = nnx.merge(graphdef, params)
            out, aux = block(carry, e0, context, rope, seq_lens, layer_kv)
            out = sharding.constrain(out, TOKENS)
            ys = (out, {k: aux[k] for k in _BLOCK0_KEYS}) if capture else None
            return out, ys

        if cfg.remat != "none":
            body = jax.checkpoint(body, policy=_remat_policy(cfg.remat), prevent_cse=not cfg.scan_layers)

        layers = (block_state, context_kv)  # context_kv None: each block projects the context itself
        if cfg.scan_layers:
            x, ys = jax.lax.scan(body, x, layers)
        else:
            per_layer = []
            for i in range(cfg.num_layers):
                x, y = body(x, jax.tree.map(lambda a: a[i], layers))
                per_layer.append(y)
            ys = jax.tree.map(lambda *a: jnp.stack(a), *per_layer) if capture else None
        if not capture:
            return x, {}
        outs, aux = ys
        captured: dict[str, Any] = {f"block{i}_out": outs[i] for i in range(cfg.num_layers)}
        captured.update({f"block0_{k}": v[0] for k, v in aux.items()})
        return x, captured

    def __call__(
        self,
        latents: Float[Array, "b f h w c"],
        timesteps: Float[Array, "b f"],
        context: Float[Array, "b lc text_dim"],
    ) -> Float[Array, "b f h w c"]:
        """Official text-conditioned forward with one timestep per latent frame (no padding).

        Args:
          latents: channels-last latent video, ``c = in_dim``.
          timesteps: Wan units [0, 1000], one per latent frame (0 for clean conditioning frames).
          context: text encoder features, ``lc <= text_len`` rows (zero-padded to ``text_len``).

        Returns:
          The raw prediction, ``[b, f, h, w, out_dim]`` float32.
        """
        b, f, h, w, _ = latents.shape
        check_shape("latents", latents, (None, None, None, None, self.cfg.in_dim))
        check_shape("timesteps", timesteps, (b, f // self.cfg.patch_size[0]))
        grid = (f // self.cfg.patch_size[0], h // self.cfg.patch_size[1], w // self.cfg.patch_size[2])
        out = self.forward_tokens(
            self.patchify(latents), self.grid_positions(b, grid), self.embed_time(timesteps), self.embed_text(context)
        )
        return self.unpatchify(out, grid)


_BLOCK0_KEYS = ("self_attn_out", "cross_attn_out", "ffn_out", "sa_q_roped", "sa_k_roped", "sa_v", "sa_attn")
