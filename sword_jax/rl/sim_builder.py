"""The one builder of the world-model learned simulator that imagined rollouts run in.

GRPO (:func:`sword_jax.pipeline.grpo.world_model_setup`), the public API
(:func:`sword_jax.api.learned_simulator`) and ``benchmarks.bench_imagined_rollout`` all call
:func:`build_simulator`, so the speed the benchmark reports is the speed GRPO gets. It takes the
trained weights as they are stored and sets up their inference form by ``precision``:

* ``fast`` (default): the VAE decodes in bfloat16 with the sub-pixel x2 upsampling (the same
  result as the official nearest-x2-then-conv from the low-resolution frame, 4/9 of the
  multiply-adds) and its convolution and attention weights stored in bfloat16; the world model's
  16-bit-compute layers keep their weights in that dtype
  (:func:`sword_jax.precision.store_in_compute_dtype`: bit-identical outputs, half the memory).
  Frames differ from the float32 path by bfloat16 rounding (``FAST_FRAME_TOL`` on the tiny model).
* ``float32``: the exact path the float32 parity tests check: the VAE decodes in float32 at
  ``Precision.HIGHEST`` with the official ``repeat`` upsampling, every weight as loaded.

Either way the world model computes in its own ``model.compute_dtype`` (a training choice) and its
sampler does the actions' work once per chunk (:class:`sword_jax.world_model.sampler.ConditionedModelFn`).

Microbatches: the rollout runs the simulator over its trajectories in ``rl.imagined.sim_microbatches``
slices; 0 (default) lets the simulator choose (:func:`sword_jax.rl.rollout.microbatches_for`): the
fewest slices of at most ``sim.max_slice`` trajectories each, where ``max_slice`` (:func:`max_slice_trajectories`) holds the
decoder's full-resolution features of a slice to what fit one H100 beside the 5B world model (8
trajectories of the Wan 2.2 decoder at 256 px, issue 42).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import nnx

from sword_jax.precision import store_in_compute_dtype
from sword_jax.rl.learned_simulator import LearnedSimulator
from sword_jax.rl.world_model_sim import world_model_simulator
from sword_jax.vae.layers import CausalConv3d
from sword_jax.vae.model import set_conv_impl

PRECISIONS = ("fast", "float32")
FAST_FRAME_TOL = 0.05  # max |fast - float32| of decoded frames in [0, 1] on the tiny model (bfloat16 rounding)
# Decoder features held per slice, in trajectories x frame pixels x full-resolution decoder width: 8 trajectories
# of the Wan 2.2 decoder (width 256) at 256 px fit an H100 beside the 5B world model (49 GB peak), 32 did not.
SLICE_FEATURE_BUDGET = 8 * 256 * 256 * 256
# VAE weights read only through ``.astype(compute dtype)`` (convolutions, attention projections); norms stay float32.
VAE_CAST_PARAMS = ("kernel", "bias", "conv_kernel", "conv_bias", "qkv_kernel", "qkv_bias", "proj_kernel", "proj_bias")


def check_precision(precision: str) -> None:
    if precision not in PRECISIONS:
        raise ValueError(f"simulator precision must be one of {PRECISIONS}, got {precision!r}")


def inference_vae(vae_graphdef: nnx.GraphDef, vae_state: Any, precision: str) -> tuple[nnx.GraphDef, Any]:
    """The VAE set up for rollout decoding (module docstring); the causal-convolution form stays the VAE's own."""
    check_precision(precision)
    model = nnx.merge(vae_graphdef, vae_state)
    causal_conv = next(m.impl for _, m in nnx.iter_modules(model) if isinstance(m, CausalConv3d))
    fast = precision == "fast"
    set_conv_impl(model, causal_conv=causal_conv, upsample="subpixel" if fast else "repeat")
    model.compute_dtype = "bfloat16" if fast else "float32"
    graphdef, state = nnx.split(model)
    if fast:
        def store(path, leaf):
            name = next((k.key for k in reversed(path) if isinstance(k, jax.tree_util.DictKey)), None)
            return leaf.astype(jnp.bfloat16) if name in VAE_CAST_PARAMS and leaf.dtype == jnp.float32 else leaf

        state = jax.tree_util.tree_map_with_path(store, state)
    return graphdef, state


def max_slice_trajectories(vae_state: Any, frame_size: int) -> int:
    """Trajectories per simulator microbatch whose decoder features fit ``SLICE_FEATURE_BUDGET``."""
    width = vae_state["decoder"]["head_conv"]["kernel"].shape[-2]  # the full-resolution level's channels
    return max(1, SLICE_FEATURE_BUDGET // (frame_size * frame_size * width))


def stored_for_simulator(wm_graphdef: nnx.GraphDef, wm_state: Any, precision: str) -> Any:
    """The world model's weights as the simulator of ``precision`` holds them (``fast``: each 16-bit-compute
    layer's in its compute dtype; ``float32``: as given), e.g. a refresh's fine-tuned float32 weights put
    into a simulator :func:`build_simulator` made."""
    check_precision(precision)
    return store_in_compute_dtype(wm_graphdef, wm_state) if precision == "fast" else wm_state


def build_simulator(
    wm_graphdef: nnx.GraphDef,
    wm_state: Any,
    vae_graphdef: nnx.GraphDef,
    vae_state: Any,
    *,
    precision: str = "fast",
    **options: Any,
) -> LearnedSimulator:
    """The learned simulator (world model + streaming VAE decode) as every imagined rollout runs it.

    Args:
      wm_graphdef / wm_state: the split world model as loaded (``wm_state`` one state or ``(params, buffers)``).
      vae_graphdef / vae_state: the split VAE as loaded.
      precision: ``fast`` or ``float32`` (module docstring); ``rl.imagined.sim_precision`` for GRPO.
      options: :func:`~sword_jax.rl.world_model_sim.world_model_simulator`'s keyword arguments (``flow_cfg``,
        ``frame_size``, geometry, ``sample_steps``, proprio).

    Returns:
      The simulator, with ``max_slice`` set for the rollout's microbatches
      (:func:`sword_jax.rl.rollout.microbatches_for`).
    """
    check_precision(precision)
    vae_graphdef, vae_state = inference_vae(vae_graphdef, vae_state, precision)
    wm_state = stored_for_simulator(wm_graphdef, wm_state, precision)
    sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, **options)
    return sim.replace(max_slice=max_slice_trajectories(vae_state, sim.frame_size))
