"""A compact vision-language-action (VLA) policy with a discretised action-chunk head.

Inputs: the agentview frame (optionally the wrist frame), the language instruction as UTF-8
bytes, and the proprioceptive state. Output: logits over ``action_bins`` bins for each of the
``chunk_len x action_dim`` action tokens of one chunk (8 x 7 by default), decoded in parallel
from learned action-query tokens (OpenVLA-OFT's parallel decoding).

Why discretised tokens (OpenVLA, 256 bins per dimension) rather than a Gaussian:

* GRPO needs exact, cheap log-probabilities of the sampled actions under the current, old and
  reference policies; a categorical over bins gives them exactly with no squashing correction.
* A categorical is multimodal (grasp left vs right of an object); a diagonal Gaussian averages
  the modes, which both hurts behaviour cloning and makes sampled rollouts incoherent.
* Its entropy cannot collapse through a learned std shrinking to zero, a common failure of
  Gaussian PPO fine-tuning from a BC start; temperature controls exploration instead.
* Per-token ratios give per-dimension clipping, as the GRPO-for-OpenVLA recipes use.

The quantisation error (half a bin, 1/256 of the range) is far below the demonstrations' noise.

Language is read from the TEXT (bytes -> embeddings -> transformer), never a task id, so
instructions that differ in a single word ("... on the plate" vs "... on the stove") map to
different token sequences and different actions.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float, Int

from sword_jax.rl.config import RLConfig
from sword_jax.sharding import constrain

PAD_BYTE = 0  # token 0 is padding; byte b is token b + 1


def tokenize_instructions(instructions: Sequence[str] | str, max_bytes: int) -> np.ndarray:
    """UTF-8 byte tokens of lower-cased instructions, padded / truncated to ``max_bytes``.

    Args:
      instructions: one string or a sequence of strings.
      max_bytes: token sequence length.

    Returns:
      ``int32 [n, max_bytes]`` tokens in ``[0, 256]``; 0 is padding.
    """
    if isinstance(instructions, str):
        instructions = [instructions]
    out = np.zeros((len(instructions), max_bytes), np.int32)
    for i, text in enumerate(instructions):
        if not isinstance(text, str) or not text.strip():
            raise ValueError(f"instruction {i} must be a non-empty string, got {text!r}")
        raw = np.frombuffer(text.strip().lower().encode("utf-8"), np.uint8)[:max_bytes]
        out[i, : raw.size] = raw.astype(np.int32) + 1
    return out


def bin_centers(num_bins: int) -> Float[Array, " bins"]:
    """Centres of ``num_bins`` uniform bins over the normalised action range [-1, 1]."""
    edges = jnp.linspace(-1.0, 1.0, num_bins + 1, dtype=jnp.float32)
    return (edges[:-1] + edges[1:]) * jnp.float32(0.5)


def actions_to_tokens(actions: Float[Array, "... a"], num_bins: int) -> Int[Array, "... a"]:
    """Bin index of each (clipped to [-1, 1]) action value."""
    scaled = (jnp.clip(actions.astype(jnp.float32), -1.0, 1.0) + 1.0) * jnp.float32(num_bins / 2.0)
    return jnp.clip(jnp.floor(scaled).astype(jnp.int32), 0, num_bins - 1)


def tokens_to_actions(tokens: Int[Array, "... a"], num_bins: int) -> Float[Array, "... a"]:
    """Bin centre of each token (inverse of :func:`actions_to_tokens` up to half a bin)."""
    return bin_centers(num_bins)[tokens]


def token_log_probs(logits: Float[Array, "... bins"], tokens: Int[Array, "..."]) -> Float[Array, "..."]:
    """log pi(token) under categorical ``logits`` (float32)."""
    logp = jax.nn.log_softmax(logits.astype(jnp.float32), axis=-1)
    return jnp.take_along_axis(logp, tokens[..., None], axis=-1)[..., 0]


SIM_PROPRIO_DIM = 8  # the simulator's layout: ee xyz (3), ee axis-angle (3), finger positions (2)


def proprio_feature_dim(cfg: RLConfig) -> int:
    """Width of the policy's proprio features: 11 for ``rot6d`` (xyz, two rotation columns, fingers)."""
    return 11 if cfg.policy.proprio_encoding == "rot6d" else cfg.proprio_dim


def axis_angle_to_matrix(axis_angle: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """Rodrigues' formula; smooth at zero angle (series form of sin(t)/t and (1-cos t)/t^2)."""
    v = axis_angle.astype(jnp.float32)
    theta2 = jnp.sum(v * v, axis=-1)[..., None, None]
    small = theta2 < 1e-8
    theta = jnp.sqrt(jnp.where(small, 1.0, theta2))
    a = jnp.where(small, 1.0 - theta2 / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta2 / 24.0, (1.0 - jnp.cos(theta)) / jnp.where(small, 1.0, theta2))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = jnp.zeros_like(x)
    k = jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1), jnp.stack([-y, x, zero], -1)], -2)
    eye = jnp.eye(3, dtype=jnp.float32)
    return eye + a * k + b * (k @ k)


def proprio_features(proprio: Float[Array, "... p"], encoding: str) -> Float[Array, "... f"]:
    """Continuous proprio features.

    The simulator's (LIBERO's) 8-D proprio stores the end-effector orientation as an axis-angle,
    which flips sign when the rotation passes 180 degrees -- as the expert's grasps do -- so two
    nearly equal poses can look maximally different. ``rot6d`` replaces it by the first two
    columns of the rotation matrix (continuous everywhere); ``raw`` passes proprio through.

    Args:
      proprio: ``[..., 8]`` (``rot6d``) or ``[..., P]`` (``raw``).
      encoding: ``rot6d`` | ``raw``.

    Returns:
      ``[..., 11]`` (xyz, rotation columns 0 and 1, fingers) or the input.
    """
    if encoding == "raw":
        return proprio.astype(jnp.float32)
    if proprio.shape[-1] != SIM_PROPRIO_DIM:
        raise ValueError(f"rot6d proprio encoding needs the simulator's 8-D proprio, got {proprio.shape}")
    proprio = proprio.astype(jnp.float32)
    rot = axis_angle_to_matrix(proprio[..., 3:6])
    columns = jnp.concatenate([rot[..., :, 0], rot[..., :, 1]], axis=-1)  # (..., 6)
    return jnp.concatenate([proprio[..., :3], columns, proprio[..., 6:8]], axis=-1)


class NormStat(nnx.Variable):
    """A data statistic stored with the policy (saved and restored with it, never trained)."""


def _dense(din: int, dout: int, axes: tuple[str, str], rngs: nnx.Rngs, scale: float = 1.0) -> nnx.Linear:
    init = nnx.initializers.variance_scaling(scale, "fan_in", "truncated_normal")
    return nnx.Linear(din, dout, kernel_init=nnx.with_partitioning(init, axes), rngs=rngs)


class _Block(nnx.Module):
    """Pre-norm transformer block with a key padding mask."""

    def __init__(self, width: int, heads: int, rngs: nnx.Rngs):
        self.norm1 = nnx.LayerNorm(width, rngs=rngs)
        self.attn = nnx.MultiHeadAttention(
            num_heads=heads, in_features=width, qkv_features=width, decode=False, rngs=rngs,
            kernel_init=nnx.with_partitioning(nnx.initializers.lecun_normal(), ("embed", "heads")),
        )
        self.norm2 = nnx.LayerNorm(width, rngs=rngs)
        self.up = _dense(width, 4 * width, ("embed", "mlp"), rngs)
        self.down = _dense(4 * width, width, ("mlp", "embed"), rngs, scale=0.5)

    def __call__(self, x: Float[Array, "b n d"], key_mask: Float[Array, "b n"]) -> Float[Array, "b n d"]:
        mask = nnx.make_attention_mask(jnp.ones(key_mask.shape, jnp.bool_), key_mask > 0)
        x = x + self.attn(self.norm1(x), mask=mask)
        x = x + self.down(jax.nn.gelu(self.up(self.norm2(x))))
        return constrain(x, ("batch", "length", "embed"))


class ImageEncoder(nnx.Module):
    """Three stride-2 convolutions: ``[b, H, W, 3]`` in [0, 1] -> ``[b, (H/8)*(W/8), width]`` tokens."""

    def __init__(self, width: int, rngs: nnx.Rngs):
        chans = (width // 4, width // 2, width)
        cin = 3
        self.convs = nnx.List()
        for c in chans:
            self.convs.append(nnx.Conv(cin, c, (4, 4), strides=(2, 2), padding="SAME", rngs=rngs))
            cin = c
        self.norm = nnx.LayerNorm(width, rngs=rngs)

    def __call__(self, frames: Float[Array, "b h w 3"]) -> Float[Array, "b n d"]:
        x = frames.astype(jnp.float32) * jnp.float32(2.0) - jnp.float32(1.0)
        for conv in self.convs:
            x = jax.nn.gelu(conv(x))
        b, h, w, d = x.shape
        return self.norm(x.reshape(b, h * w, d))  # (B, N, D)


class VLAPolicy(nnx.Module):
    """Frames + instruction bytes + proprio -> categorical logits of one action chunk.

    Args:
      cfg: the RL config (width, layers, heads, image size, bins, chunk shape).
      rngs: parameter randomness.
    """

    def __init__(self, cfg: RLConfig, *, use_wrist: bool = False, rngs: nnx.Rngs):
        cfg.validate()
        self.cfg = cfg
        self.use_wrist = use_wrist
        d = cfg.policy.width
        n_img = (cfg.image_size // 8) ** 2
        self.image_encoder = ImageEncoder(d, rngs)
        self.wrist_encoder = ImageEncoder(d, rngs) if use_wrist else None
        self.byte_embed = nnx.Embed(257, d, rngs=rngs)
        self.text_pos = nnx.Param(jax.random.normal(rngs.params(), (cfg.policy.max_instruction_bytes, d), jnp.float32) * 0.02)
        n_views = 2 if use_wrist else 1
        self.image_pos = nnx.Param(jax.random.normal(rngs.params(), (n_views * n_img, d), jnp.float32) * 0.02)
        n_feat = max(proprio_feature_dim(cfg), 1)
        # Normalisation of the proprio features: set from the demonstrations (set_proprio_stats).
        self.proprio_mean = NormStat(jnp.zeros((n_feat,), jnp.float32))
        self.proprio_std = NormStat(jnp.ones((n_feat,), jnp.float32))
        self.proprio_proj = _dense(n_feat, d, ("action", "embed"), rngs)
        self.proprio_missing = nnx.Param(jnp.zeros((d,), jnp.float32))
        self.action_queries = nnx.Param(jax.random.normal(rngs.params(), (cfg.chunk_len, d), jnp.float32) * 0.02)
        self.text_blocks = nnx.List([_Block(d, cfg.policy.heads, rngs) for _ in range(cfg.policy.layers)])
        self.fusion_blocks = nnx.List([_Block(d, cfg.policy.heads, rngs) for _ in range(cfg.policy.layers)])
        self.out_norm = nnx.LayerNorm(d, rngs=rngs)
        self.head = _dense(d, cfg.action_dim * cfg.action_bins, ("embed", "mlp"), rngs, scale=0.1)

    def encode_text(self, tokens: Int[Array, "b l"]) -> tuple[Float[Array, "b l d"], Float[Array, "b l"]]:
        """Byte tokens -> contextual text features and their validity mask."""
        if tokens.shape[-1] != self.cfg.policy.max_instruction_bytes:
            raise ValueError(f"instruction tokens must have length {self.cfg.policy.max_instruction_bytes}, got {tokens.shape}")
        mask = (tokens != PAD_BYTE).astype(jnp.float32)
        x = self.byte_embed(tokens) + self.text_pos[...][None]
        for block in self.text_blocks:
            x = block(x, mask)
        return x, mask

    def __call__(
        self,
        frames: Float[Array, "b h w 3"],
        instruction_tokens: Int[Array, "b l"],
        proprio: Float[Array, "b p"],
        proprio_valid: Float[Array, " b"] | None = None,
        wrist_frames: Float[Array, "b h w 3"] | None = None,
    ) -> Float[Array, "b t a bins"]:
        """Action-token logits.

        Args:
          frames: agentview frames in [0, 1], resized to ``cfg.image_size``.
          instruction_tokens: from :func:`tokenize_instructions`.
          proprio: proprioceptive state ``[b, cfg.proprio_dim]`` (ignored where invalid).
          proprio_valid: 1 where ``proprio`` is real, 0 where the simulator cannot provide it
            (a learned "missing" embedding is used instead); default all valid.
          wrist_frames: wrist-camera frames, required iff the policy was built with ``use_wrist``.

        Returns:
          float32 logits ``[b, chunk_len, action_dim, action_bins]``.
        """
        cfg = self.cfg
        b = frames.shape[0]
        if frames.shape[1:] != (cfg.image_size, cfg.image_size, 3):
            raise ValueError(f"frames must be [b, {cfg.image_size}, {cfg.image_size}, 3], got {frames.shape}")
        if proprio.shape != (b, cfg.proprio_dim):
            raise ValueError(f"proprio must be [{b}, {cfg.proprio_dim}], got {proprio.shape}")
        text, text_mask = self.encode_text(instruction_tokens)
        image = self.image_encoder(frames)
        if self.use_wrist:
            if wrist_frames is None:
                raise ValueError("this policy was built with use_wrist=True: pass wrist_frames")
            image = jnp.concatenate([image, self.wrist_encoder(wrist_frames)], axis=1)
        image = image + self.image_pos[...][None]
        valid = jnp.ones((b,), jnp.float32) if proprio_valid is None else proprio_valid.astype(jnp.float32)
        if cfg.proprio_dim:
            feats = proprio_features(proprio, cfg.policy.proprio_encoding)
            mean = jax.lax.stop_gradient(self.proprio_mean[...])
            std = jax.lax.stop_gradient(self.proprio_std[...])
            p_tok = self.proprio_proj((feats - mean) / std)
        else:
            p_tok = jnp.zeros((b, cfg.policy.width), jnp.float32)
        p_tok = valid[:, None] * p_tok + (1.0 - valid[:, None]) * self.proprio_missing[...][None]
        queries = jnp.broadcast_to(self.action_queries[...][None], (b, cfg.chunk_len, cfg.policy.width))
        x = jnp.concatenate([text, image, p_tok[:, None], queries], axis=1)  # (B, L + N + 1 + T, D)
        mask = jnp.concatenate([text_mask, jnp.ones((b, x.shape[1] - text.shape[1]), jnp.float32)], axis=1)
        for block in self.fusion_blocks:
            x = block(x, mask)
        out = self.head(self.out_norm(x[:, -cfg.chunk_len :]))  # (B, T, A * bins)
        return out.reshape(b, cfg.chunk_len, cfg.action_dim, cfg.action_bins).astype(jnp.float32)


def sample_chunk(
    logits: Float[Array, "b t a bins"], *, key: jax.Array, temperature: float = 1.0
) -> tuple[Int[Array, "b t a"], Float[Array, "b t a"]]:
    """Samples action tokens at ``temperature``; returns them and their log-probs under the
    distribution they were sampled from (:func:`sampling_log_probs`), which is what GRPO's ratio
    divides by and what its update recomputes."""
    tokens = jax.random.categorical(key, logits / jnp.float32(temperature), axis=-1)
    return tokens, sampling_log_probs(logits, tokens, temperature)


def sampling_log_probs(
    logits: Float[Array, "... bins"], tokens: Int[Array, "..."], temperature: float = 1.0
) -> Float[Array, "..."]:
    """Log-probs of ``tokens`` under the tempered policy ``softmax(logits / temperature)``.

    GRPO samples from this distribution and must differentiate its log-probs, not the untempered
    ones: the score of the untempered policy has a non-zero mean under tempered samples
    (``E[grad log softmax(z)[a]] = p_T - p_1``), a drift that at temperature 0.7 raised the policy's
    per-token entropy from 2.0 to 3.7 nats and its success from 0.40 to 0.03 within 50 steps on
    ``small`` (README, issue 17).
    """
    return token_log_probs(logits / jnp.float32(temperature), tokens)


def greedy_chunk(logits: Float[Array, "b t a bins"]) -> Int[Array, "b t a"]:
    """Most likely token per action dimension (deterministic evaluation)."""
    return jnp.argmax(logits, axis=-1).astype(jnp.int32)


def resize_frames(frames: Float[Array, "... h w 3"], size: int) -> Float[Array, "... s s 3"]:
    """Resizes float frames in [0, 1] (or uint8) to ``size x size`` for the policy / reward model."""
    if frames.dtype == jnp.uint8:
        frames = frames.astype(jnp.float32) / jnp.float32(255.0)
    frames = frames.astype(jnp.float32)
    if frames.shape[-3:-1] == (size, size):
        return frames
    shape = frames.shape[:-3] + (size, size, frames.shape[-1])
    return jax.image.resize(frames, shape, method="linear", antialias=True)


def build_policy(
    cfg: RLConfig, *, seed: int = 0, use_wrist: bool = False, mesh=None, rules=None
) -> tuple[nnx.GraphDef, nnx.State]:
    """``(graphdef, params)`` of a fresh policy; born sharded over ``mesh`` when given."""
    from sword_jax import sharding

    def factory():
        return VLAPolicy(cfg, use_wrist=use_wrist, rngs=nnx.Rngs(seed))

    if mesh is not None:
        return sharding.create_sharded(factory, mesh, rules or sharding.DEFAULT_RULES)
    with nnx.use_eager_sharding(False):
        return nnx.split(factory())


def compute_proprio_stats(proprio: np.ndarray, cfg: RLConfig, *, min_std: float = 1e-2) -> dict[str, np.ndarray]:
    """Mean and std of the policy's proprio features over demonstration steps ``[..., P]``.

    ``min_std`` keeps near-constant features (e.g. a rotation column the task never changes)
    from being blown up into noise.
    """
    feats = np.asarray(proprio_features(jnp.asarray(proprio.reshape(-1, proprio.shape[-1])), cfg.policy.proprio_encoding))
    return {"mean": feats.mean(0).astype(np.float32), "std": np.maximum(feats.std(0), min_std).astype(np.float32)}


def set_proprio_stats(params: nnx.State, stats: dict[str, np.ndarray]) -> nnx.State:
    """``params`` with the proprio normalisation replaced by ``stats`` (from :func:`compute_proprio_stats`)."""
    mean, std = np.asarray(stats["mean"], np.float32), np.asarray(stats["std"], np.float32)
    if mean.shape != params["proprio_mean"][...].shape or std.shape != mean.shape or np.any(std <= 0):
        raise ValueError(f"proprio stats must be two {params['proprio_mean'][...].shape} arrays with std > 0, "
                         f"got {mean.shape}/{std.shape}")
    out = jax.tree.map(lambda x: x, params)
    out["proprio_mean"] = out["proprio_mean"].replace(jnp.asarray(mean).astype(out["proprio_mean"][...].dtype))
    out["proprio_std"] = out["proprio_std"].replace(jnp.asarray(std).astype(out["proprio_std"][...].dtype))
    return out


def trainable_mask(params: nnx.State) -> Any:
    """Pytree of bools like ``params``: False for the stored statistics (no weight decay on them)."""
    stats = {"proprio_mean", "proprio_std"}
    return jax.tree_util.tree_map_with_path(
        lambda path, _: not any(getattr(k, "key", None) in stats for k in path), params)


def policy_logits(graphdef: nnx.GraphDef, params: nnx.State, *args, **kwargs) -> Float[Array, "b t a bins"]:
    """Functional forward pass: merges ``(graphdef, params)`` and calls the policy."""
    return nnx.merge(graphdef, params)(*args, **kwargs)
