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

Decoder (``rl.imagined.decoder``): the VAE's (default), or a light decoder distilled from it
(:mod:`sword_jax.vae.light_decoder`, ``light_decoder=``) that streams the same latents to frames at its
own resolution (the policy's, by default), in bfloat16 under ``fast`` and float32 at the highest
precision under ``float32``. The VAE is still given: its spatial factor fixes the world model's latent
size, and GRPO encodes the start frames with it.

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
from sword_jax.vae import api as vae_api
from sword_jax.vae import light_decoder as light
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


def inference_light_decoder(graphdef: nnx.GraphDef, state: Any, precision: str) -> tuple[nnx.GraphDef, Any]:
    """The light decoder set up for rollout decoding: bfloat16 convolutions under ``fast``, float32 at the
    highest precision under ``float32`` (its weights stay float32: a few MB)."""
    check_precision(precision)
    model = nnx.merge(graphdef, state)
    model.compute_dtype = "bfloat16" if precision == "fast" else "float32"
    return nnx.split(model)


def light_max_slice(graphdef: nnx.GraphDef, state: Any, latent_size: int) -> int:
    """Trajectories per simulator microbatch whose light-decoder features fit ``SLICE_FEATURE_BUDGET`` (its
    widest activation per frame, at the head)."""
    model = nnx.merge(graphdef, state)
    head_in = model.head.kernel[...].shape[-2]
    side = latent_size * model.scale // model.head_patch
    return max(1, SLICE_FEATURE_BUDGET // (side * side * head_in))


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
    light_decoder: tuple[nnx.GraphDef, Any] | None = None,
    **options: Any,
) -> LearnedSimulator:
    """The learned simulator (world model + streaming VAE decode) as every imagined rollout runs it.

    Args:
      wm_graphdef / wm_state: the split world model as loaded (``wm_state`` one state or ``(params, buffers)``).
      vae_graphdef / vae_state: the split VAE as loaded.
      precision: ``fast`` or ``float32`` (module docstring); ``rl.imagined.sim_precision`` for GRPO.
      light_decoder: ``(graphdef, state)`` of a light decoder (:func:`sword_jax.load.load_light_decoder`) that
        decodes the frames instead of the VAE (``rl.imagined.decoder=light``); None = the VAE's decoder.
      options: :func:`~sword_jax.rl.world_model_sim.world_model_simulator`'s keyword arguments (``flow_cfg``,
        ``frame_size`` (the VAE's frames: the world model's latent size is ``frame_size`` over the VAE's
        spatial factor), geometry, ``sample_steps``, proprio).

    Returns:
      The simulator, with ``max_slice`` set for the rollout's microbatches
      (:func:`sword_jax.rl.rollout.microbatches_for`); with a light decoder its ``frame_size`` is the light
      decoder's.
    """
    check_precision(precision)
    wm_state = stored_for_simulator(wm_graphdef, wm_state, precision)
    if light_decoder is not None:
        light_graphdef, light_state = inference_light_decoder(*light_decoder, precision)
        latent_size = options.pop("latent_size", None) or options["frame_size"] // vae_api.factors(vae_graphdef,
                                                                                                  vae_state)[1]
        _, scale, temporal, _ = light.attributes(light_graphdef, light_state)
        if temporal != vae_api.factors(vae_graphdef, vae_state)[0]:
            raise ValueError(f"light decoder: {temporal} frames per latent, the VAE makes "
                             f"{vae_api.factors(vae_graphdef, vae_state)[0]}")
        options = dict(options, frame_size=latent_size * scale, latent_size=latent_size)
        sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state,
                                    light_decoder=(light_graphdef, light_state), **options)
        return sim.replace(max_slice=light_max_slice(light_graphdef, light_state, latent_size))
    vae_graphdef, vae_state = inference_vae(vae_graphdef, vae_state, precision)
    sim = world_model_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, **options)
    return sim.replace(max_slice=max_slice_trajectories(vae_state, sim.frame_size))
