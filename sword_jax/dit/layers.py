"""Building blocks of the Wan DiT: linear layers with logical axes, norms, sinusoids, 3D RoPE, attention.

Everything numerically delicate follows the official Wan 2.2 ``WanModel`` (see
``shared/reference/wan22/README.md``): the timestep sinusoid is ``[cos, sin]`` with the exponent
divided by ``half``; RoPE splits each head's rotation pairs into frame / height / width groups,
uses each group's own width in the exponent and rotates *adjacent* feature pairs ``(2j, 2j+1)``;
q/k RMSNorm spans the full model width; LayerNorms use eps 1e-6.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Float, Int

ROPE_MAX_POSITIONS = 1024  # rows of the official RoPE table (positions per axis)


def dtype_of(name: str) -> jnp.dtype:
    return {"float32": jnp.float32, "bfloat16": jnp.bfloat16}[name]


def matmul_precision(compute_dtype: jnp.dtype) -> jax.lax.Precision | None:
    """Full fp32 matmuls when computing in float32 (GPUs otherwise use TF32 passes)."""
    return jax.lax.Precision.HIGHEST if compute_dtype == jnp.float32 else None


def linear(
    in_features: int,
    out_features: int,
    axes: tuple[str | None, str | None],
    *,
    compute_dtype: jnp.dtype,
    param_dtype: jnp.dtype,
    rngs: nnx.Rngs,
    kernel_init=nnx.initializers.xavier_uniform(),
    bias_init=nnx.initializers.zeros_init(),
) -> nnx.Linear:
    """``nnx.Linear`` with logical axis names on kernel ``axes`` and bias ``(axes[1],)``."""
    return nnx.Linear(
        in_features,
        out_features,
        dtype=compute_dtype,
        param_dtype=param_dtype,
        precision=matmul_precision(compute_dtype),
        kernel_init=nnx.with_partitioning(kernel_init, axes),
        bias_init=nnx.with_partitioning(bias_init, (axes[1],)),
        rngs=rngs,
    )


def layer_norm(x: Float[Array, "... d"], eps: float) -> Float[Array, "... d"]:
    """LayerNorm without affine, computed in float32."""
    x = x.astype(jnp.float32)
    mean = jnp.mean(x, axis=-1, keepdims=True)
    var = jnp.mean(jnp.square(x - mean), axis=-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + jnp.float32(eps))


class AffineLayerNorm(nnx.Module):
    """LayerNorm with weight and bias (``norm3`` of a Wan block)."""

    def __init__(self, dim: int, eps: float, *, param_dtype: jnp.dtype):
        self.eps = eps
        self.scale = nnx.Param(jnp.ones((dim,), param_dtype), sharding=("embed",))
        self.bias = nnx.Param(jnp.zeros((dim,), param_dtype), sharding=("embed",))

    def __call__(self, x: Float[Array, "... d"]) -> Float[Array, "... d"]:
        return layer_norm(x, self.eps) * self.scale[...].astype(jnp.float32) + self.bias[...].astype(jnp.float32)


class RMSNorm(nnx.Module):
    """RMSNorm over the last axis, in float32: ``x * rsqrt(mean(x^2) + eps) * weight``."""

    def __init__(self, dim: int, eps: float, axis_name: str, *, param_dtype: jnp.dtype):
        self.eps = eps
        self.scale = nnx.Param(jnp.ones((dim,), param_dtype), sharding=(axis_name,))

    def __call__(self, x: Float[Array, "... d"]) -> Float[Array, "... d"]:
        x32 = x.astype(jnp.float32)
        normed = x32 * jax.lax.rsqrt(jnp.mean(jnp.square(x32), axis=-1, keepdims=True) + jnp.float32(self.eps))
        return (normed * self.scale[...].astype(jnp.float32)).astype(x.dtype)


def _split_mantissa(values: np.ndarray, parts: int, bits: int = 12) -> list[np.ndarray]:
    """Splits float64 constants into float32 pieces of at most ``bits`` significant bits each."""
    pieces, rest = [], np.asarray(values, np.float64)
    for _ in range(parts):
        piece = _truncate_np(rest.astype(np.float32), bits)
        pieces.append(piece)
        rest = rest - piece.astype(np.float64)
    pieces.append(rest.astype(np.float32))
    return pieces


def _truncate_np(x: np.ndarray, bits: int) -> np.ndarray:
    mask = np.uint32((0xFFFFFFFF << (23 - bits + 1)) & 0xFFFFFFFF)
    return (x.view(np.uint32) & mask).view(np.float32)


def _truncate(x: Float[Array, "..."], bits: int = 12) -> Float[Array, "..."]:
    """Keeps ``bits`` significant bits of a float32 (exact: the remainder ``x - result`` is exact)."""
    mask = jnp.uint32((0xFFFFFFFF << (23 - bits + 1)) & 0xFFFFFFFF)
    return jax.lax.bitcast_convert_type(jax.lax.bitcast_convert_type(x, jnp.uint32) & mask, jnp.float32)


def timestep_sinusoid(t: Float[Array, "*batch"], freq_dim: int) -> Float[Array, "*batch freq_dim"]:
    """Wan's sinusoidal timestep embedding ``[cos(t w_j), sin(t w_j)]``, ``w_j = 10000^(-j/half)``.

    The official code evaluates this in float64. With x64 enabled we do the same; otherwise the
    angle ``t * w_j`` is formed from exact float32 partial products (12-bit splits of ``t`` and of
    the float64 ``w_j``) that are each reduced modulo 2*pi before summing, which matches the
    float64 result to ~1e-6 for t in [0, 1000] (plain float32 would be off by up to 3e-5).

    Args:
      t: timesteps, any shape, Wan units ([0, 1000]).
      freq_dim: even embedding width.

    Returns:
      float32 embedding of shape ``t.shape + (freq_dim,)``.
    """
    half = freq_dim // 2
    omega = np.power(10000.0, -np.arange(half, dtype=np.float64) / half)
    if jax.config.jax_enable_x64:
        angle = t.astype(jnp.float64)[..., None] * jnp.asarray(omega, jnp.float64)
        return jnp.concatenate([jnp.cos(angle), jnp.sin(angle)], axis=-1).astype(jnp.float32)
    t32 = t.astype(jnp.float32)[..., None]
    t_hi = _truncate(t32)
    t_lo = t32 - t_hi
    w_parts = [jnp.asarray(p) for p in _split_mantissa(omega, parts=2)]  # 12 + 12 bits + rest
    two_pi = [jnp.float32(p) for p in _split_mantissa(np.array(2 * np.pi), parts=2)]
    inv_two_pi = jnp.float32(1.0 / (2 * np.pi))
    reduced = jnp.zeros(t32.shape[:-1] + (half,), jnp.float32)
    for t_part in (t_hi, t_lo):
        for w_part in w_parts:
            product = t_part * w_part  # exact for the 12x12-bit pieces
            turns = jnp.round(product * inv_two_pi)
            reduced = reduced + (((product - turns * two_pi[0]) - turns * two_pi[1]) - turns * two_pi[2])
    return jnp.concatenate([jnp.cos(reduced), jnp.sin(reduced)], axis=-1)


def rope_split(head_dim: int) -> tuple[int, int, int]:
    """Rotation pairs per axis (frame, height, width) of the official 3D RoPE."""
    height_width_dims = 2 * (head_dim // 6)
    frame_dims = head_dim - 2 * height_width_dims
    return frame_dims // 2, height_width_dims // 2, height_width_dims // 2


def rope_table(head_dim: int, max_positions: int = ROPE_MAX_POSITIONS, theta: float = 10000.0) -> np.ndarray:
    """The official complex128 RoPE table, ``[max_positions, head_dim // 2]``.

    Columns are ``[frame pairs | height pairs | width pairs]``; pair j of an axis with real width
    ``d_a`` rotates by ``pos * theta^(-2j / d_a)``.
    """
    columns = []
    for pairs in rope_split(head_dim):
        axis_dim = 2 * pairs
        freqs = 1.0 / np.power(theta, np.arange(0, axis_dim, 2, dtype=np.float64) / axis_dim)
        angles = np.outer(np.arange(max_positions, dtype=np.float64), freqs)
        columns.append(np.exp(1j * angles))
    return np.concatenate(columns, axis=1)


def rope_cos_sin(
    positions: Int[Array, "b l 3"], head_dim: int, valid: Float[Array, "b l"] | None = None
) -> tuple[Float[Array, "b l p"], Float[Array, "b l p"]]:
    """Per-token cos/sin of the 3D RoPE angles, from the float64 table rounded to float32.

    Args:
      positions: integer (frame, height, width) grid index of every token, each in [0, 1024).
      head_dim: attention head width (even).
      valid: 1 for real tokens, 0 for padding tokens (which are not rotated: cos 1, sin 0).

    Returns:
      ``(cos, sin)``, each ``[b, l, head_dim // 2]`` float32.
    """
    table = rope_table(head_dim)
    split = rope_split(head_dim)
    bounds = np.cumsum((0,) + split)
    cos_parts, sin_parts = [], []
    for axis in range(3):
        block = table[:, bounds[axis]:bounds[axis + 1]]
        index = jnp.clip(positions[..., axis], 0, ROPE_MAX_POSITIONS - 1)
        cos_parts.append(jnp.asarray(block.real, jnp.float32)[index])
        sin_parts.append(jnp.asarray(block.imag, jnp.float32)[index])
    cos, sin = jnp.concatenate(cos_parts, axis=-1), jnp.concatenate(sin_parts, axis=-1)
    if valid is not None:
        keep = valid.astype(jnp.float32)[..., None]
        cos = cos * keep + (jnp.float32(1) - keep)
        sin = sin * keep
    return cos, sin


def apply_rope(
    x: Float[Array, "b l n d"], cos: Float[Array, "b l p"], sin: Float[Array, "b l p"]
) -> Float[Array, "b l n d"]:
    """Rotates adjacent feature pairs ``(2j, 2j+1)`` of every head by the token's angles (in float32)."""
    b, l, n, d = x.shape
    pairs = x.astype(jnp.float32).reshape(b, l, n, d // 2, 2)  # (B, L, N, P, 2)
    real, imag = pairs[..., 0], pairs[..., 1]
    cos, sin = cos[:, :, None, :], sin[:, :, None, :]
    rotated = jnp.stack([real * cos - imag * sin, real * sin + imag * cos], axis=-1)
    return rotated.reshape(b, l, n, d).astype(x.dtype)


def resolve_attention_impl(impl: str, dtype: jnp.dtype, head_dim: int, q_len: int = 2, kv_len: int = 2) -> str | None:
    """Maps the config's ``auto|xla|cudnn`` to a ``jax.nn.dot_product_attention`` implementation.

    cuDNN's fused (flash) kernel is used for bf16/fp16 with head_dim a multiple of 8 up to 128 and
    even query/key lengths (its masked training kernels reject odd lengths). Attention that does
    not qualify -- e.g. cross-attention over the 13 action tokens of a segment, a negligible share
    of the FLOPs -- runs on XLA even under ``cudnn``.
    """
    if impl == "xla":
        return "xla"
    on_gpu = jax.default_backend() == "gpu"
    fits = dtype in (jnp.bfloat16, jnp.float16) and head_dim % 8 == 0 and head_dim <= 128
    fits = fits and q_len % 2 == 0 and kv_len % 2 == 0
    if impl == "cudnn":
        return "cudnn" if fits else "xla"
    return "cudnn" if on_gpu and fits else "xla"


def attention(
    query: Float[Array, "b lq n d"],
    key: Float[Array, "b lk n d"],
    value: Float[Array, "b lk n d"],
    *,
    key_lengths: Int[Array, " b"] | None,
    impl: str,
) -> Float[Array, "b lq n d"]:
    """Softmax attention with scale 1/sqrt(d); keys at index >= ``key_lengths[b]`` are masked."""
    implementation = resolve_attention_impl(impl, query.dtype, query.shape[-1], query.shape[1], key.shape[1])
    lengths = None if key_lengths is None else key_lengths.astype(jnp.int32)
    # jax's XLA attention promotes bf16 logits to f32 implicitly, which strict promotion rejects.
    with jax.numpy_dtype_promotion("standard"):
        return jax.nn.dot_product_attention(
            query, key, value, key_value_seq_lengths=lengths, implementation=implementation
        )


def check_shape(name: str, x: jax.Array, expected: Sequence[int | None]) -> None:
    """Raises a ValueError naming ``name`` when ``x``'s shape does not match (None = any)."""
    if len(x.shape) != len(expected) or any(e is not None and s != e for s, e in zip(x.shape, expected)):
        want = tuple("*" if e is None else e for e in expected)
        raise ValueError(f"{name}: expected shape {want}, got {tuple(x.shape)}")


def check_values(name: str, x: jax.Array, low: float | None = None, high: float | None = None) -> None:
    """Outside a trace, raises a ValueError naming ``name`` for NaN/inf or out-of-range values.

    Inside ``jit`` the values are unknown and nothing is checked (no host sync on hot paths).
    """
    try:
        values = np.asarray(x)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return  # traced: values unknown
    if not np.isfinite(values).all():
        raise ValueError(f"{name}: contains {int((~np.isfinite(values)).sum())} non-finite values")
    if low is not None and values.size and values.min() < low:
        raise ValueError(f"{name}: minimum {values.min()} is below {low}")
    if high is not None and values.size and values.max() > high:
        raise ValueError(f"{name}: maximum {values.max()} is above {high}")
