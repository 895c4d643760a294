"""benchmarks.common.jaxpr_flops against counts done by hand: matmuls, convolutions, scans, and attention in
both of JAX's forms (XLA's two dot_generals, cuDNN's one fused primitive)."""

import jax
import jax.numpy as jnp
import pytest

from benchmarks.common import jaxpr_flops


def test_matmul_conv_and_scan_counts_are_the_hand_counts():
    a, b = jnp.zeros((3, 4)), jnp.zeros((4, 5))
    assert jaxpr_flops(lambda x, y: x @ y, a, b) == 2 * 3 * 5 * 4
    x, w = jnp.zeros((1, 8, 8, 2)), jnp.zeros((3, 3, 2, 4))  # NHWC, HWIO, stride 1, SAME
    conv = lambda x, w: jax.lax.conv_general_dilated(x, w, (1, 1), "SAME",  # noqa: E731
                                                     dimension_numbers=("NHWC", "HWIO", "NHWC"))
    assert jaxpr_flops(conv, x, w) == 2 * (8 * 8 * 4) * (3 * 3) * 2
    looped = lambda x, y: jax.lax.scan(lambda c, _: (c @ y, None), x, None, length=7)[0]  # noqa: E731
    assert jaxpr_flops(looped, jnp.zeros((3, 4)), jnp.zeros((4, 4))) == 7 * 2 * 3 * 4 * 4


def test_fused_attention_counts_as_its_two_matmuls():
    batch, q_len, k_len, heads, dim = 2, 16, 32, 4, 8
    q = jnp.zeros((batch, q_len, heads, dim), jnp.bfloat16)
    k = jnp.zeros((batch, k_len, heads, dim), jnp.bfloat16)
    want = 2 * (2 * batch * heads * q_len * k_len * dim)  # Q K^T, then P V
    q32, k32 = q.astype(jnp.float32), k.astype(jnp.float32)  # cuDNN takes 16-bit inputs, XLA's form float32 here
    xla = jaxpr_flops(lambda q, k, v: jax.nn.dot_product_attention(q, k, v, implementation="xla"), q32, k32, k32)
    assert xla == want
    fused = pytest.importorskip("jax._src.cudnn.fused_attention_stablehlo")
    mp = pytest.MonkeyPatch()
    mp.setattr(fused, "check_cudnn_version", lambda: 91000)  # trace only: no cuDNN runs on a CPU
    try:
        cudnn = jaxpr_flops(lambda q, k, v: jax.nn.dot_product_attention(q, k, v, implementation="cudnn"), q, k, k)
    except Exception as err:  # this JAX traces the cuDNN form differently: nothing to count here
        pytest.skip(f"the cuDNN attention does not trace on this CPU: {err}")
    finally:
        mp.undo()
    assert cudnn == want
