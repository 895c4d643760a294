"""Imagined-rollout throughput: policy + world model (few-step sampler) + streaming VAE decode + reward model.

Measures imagined frames per second per GPU of ONE jitted :func:`sword_jax.rl.rollout.imagined_rollout`
(``lax.scan`` over chunks, vmapped over B x G trajectories) at

* ``small``: the ``sword:small`` DiT (dim 512, 8 layers) and VAE, 128x128 frames;
* ``5b_width``: the Wan 2.2 TI2V-5B width (dim 3072, ffn 14336, 24 heads) with ``--layers`` blocks
  (default 4 of the 30; a full-depth rollout costs ~30/layers times the DiT share) and the
  full-size Wan 2.2 VAE decoder, 256x256 frames, bf16 compute.

Usage::

    python -m benchmarks.bench_imagined_rollout            # GPU: both configs, merges results
    python -m benchmarks.bench_imagined_rollout --tiny     # CPU smoke run (tiny shapes)

The simulator is built by :func:`sword_jax.rl.sim_builder.build_simulator`, the builder GRPO and
``sword_jax.learned_simulator`` use, at ``--precision`` (GRPO's ``rl.imagined.sim_precision``): ``fast``
(default: bf16 decode with sub-pixel upsampling, weights stored in the compute dtype) or ``float32``
(the exact decode); ``both`` runs each case fast first and then float32, side by side in one process
(fast first, because the peak-memory reading is the process's running maximum), and merges
``imagined_rollout_fast_over_float32`` (frames/s ratio, both peaks). ``--sim-microbatches 0`` (default)
lets the simulator choose them, as GRPO does (:func:`sword_jax.rl.rollout.microbatches_for`).

``--layers 30`` is the full TI2V-5B depth: its figure is written as ``imagined_frames_per_s_5b_full``
(``imagined_frames_per_s_5b_width`` otherwise). Each row carries the matmul and convolution FLOPs of
one imagined frame, counted on the rollout's jaxpr (``common.jaxpr_flops``: policy, sampler steps,
decode, reward CNN), with the DiT's (as ``bench_dit_train`` counts) and the decoder's shares beside
them, and ``ceiling_frames_per_s``, the rate at the bf16
matmul peak measured in the same process. ``--causal-conv`` picks the decoder's causal-convolution
form (``bench_vae``). A case that runs out of memory is reported and the others go on.

``--decoder light`` decodes the imagined frames with the light rollout decoder (``rl.imagined.decoder=light``:
:mod:`sword_jax.vae.light_decoder`, default width, random weights) at the policy's ``rl.image_size``, through
the same builder; its figures are written under the same keys with ``_light_decoder`` appended, and
``rollout_decode_gflop_per_frame`` records its decode FLOPs per frame beside the VAE decoder's (issue 42's
target: at most a tenth).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
from flax import nnx

import configs
from benchmarks import common
from benchmarks.bench_dit_train import forward_flops
from sword_jax import cli
from sword_jax import sharding as shd
from sword_jax.dit.action_dit import WorldModel
from sword_jax.dit.config import DiTConfig
from sword_jax.precision import parameter_bytes
from sword_jax.rl.config import PolicyConfig, RewardModelConfig, RLConfig
from sword_jax.rl.learned_simulator import StartState
from sword_jax.rl.policy import VLAPolicy, tokenize_instructions
from sword_jax.rl.reward_model import SuccessDetector, as_reward_model
from sword_jax.rl.rollout import expand_groups, imagined_rollout, microbatches_for
from sword_jax.rl.sim_builder import PRECISIONS, build_simulator, inference_light_decoder, inference_vae
from sword_jax.vae import api as vae_api
from sword_jax.vae import light_decoder as light
from sword_jax.vae.config import LightDecoderConfig, VAEConfig
from sword_jax.vae.model import WanVAE

TARGET_5B = 300.0  # imagined frames/s on one H100, full 5B model (issue 42)
TARGET_5B_LIGHT = 500.0  # the same with the light decoder at the policy's resolution (issue 42's stretch)


def _split_sharded(factory, mesh):
    return shd.create_sharded(factory, mesh, shd.DEFAULT_RULES)


def simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, *, frame_size: int, sample_steps: int, rl: RLConfig,
              precision: str, light_decoder=None):
    """The measured simulator: GRPO's builder with the tiny config's flow settings."""
    return build_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, precision=precision,
                           flow_cfg=configs.get("sword:tiny").flow, frame_size=frame_size, sample_steps=sample_steps,
                           proprio_dim=rl.proprio_dim, light_decoder=light_decoder)


def _decode_flops_per_frame(graphdef, state, latents, cache, *, light_form: bool) -> float:
    """Matmul and convolution FLOPs per frame of one streamed chunk of ``latents`` (a later chunk: ``cache``'s
    shapes only matter, so no decode is run or compiled)."""
    cache = vae_api.StreamCache(cache.features, started=True)
    if light_form:
        fn = lambda s, z, c: light.decode_chunk(graphdef, s, z, c)[0]  # noqa: E731
        frames = latents.shape[1] * light.attributes(graphdef, state)[2]
    else:
        fn = lambda s, z, c: vae_api.decode_chunk(graphdef, s, z, c, check_values=False)[0]  # noqa: E731
        frames = latents.shape[1] * vae_api.factors(graphdef, state)[0]
    return common.jaxpr_flops(fn, state, latents, cache) / frames


def run_case(name: str, dit: DiTConfig, vae: VAEConfig, frame_size: int, *, starts: int, group: int, chunks: int,
             sample_steps: int, rl: RLConfig, iters: int, precision: str = "fast", peak_tflops: float | None = None,
             sim_microbatches: int = 0, decoder: str = "full") -> dict:
    mesh = shd.make_mesh(shd.MeshConfig(data=-1))
    t0 = time.perf_counter()
    hl = frame_size // vae.spatial_factor
    wm_graphdef, wm_state = _split_sharded(lambda: WorldModel(dit, rngs=nnx.Rngs(0)), mesh)
    vae_graphdef, vae_state = _split_sharded(lambda: WanVAE(vae, rngs=nnx.Rngs(1)), mesh)
    policy_graphdef, policy_params = _split_sharded(lambda: VLAPolicy(rl, rngs=nnx.Rngs(2)), mesh)
    det_graphdef, det_params = _split_sharded(lambda: SuccessDetector(rl, rngs=nnx.Rngs(3)), mesh)
    light_decoder = None
    if decoder == "light":  # at the policy's resolution, as rl.imagined.decoder=light decodes by default
        light_decoder = _split_sharded(lambda: light.LightDecoder(
            LightDecoderConfig(), z_dim=vae.z_dim, scale=rl.image_size // hl, temporal_factor=vae.temporal_factor,
            rngs=nnx.Rngs(4)), mesh)
    sim = simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, frame_size=frame_size, sample_steps=sample_steps,
                    rl=rl, precision=precision, light_decoder=light_decoder)
    wm_state, decoder_state = sim.params  # as the simulator holds them (the precision's dtypes)
    build_s = time.perf_counter() - t0
    reward_model = as_reward_model(det_graphdef, det_params)
    n = starts * group
    sim_microbatches = microbatches_for(n, sim_microbatches, sim.max_slice)
    start = StartState(
        frame=jax.random.uniform(jax.random.key(0), (starts, frame_size, frame_size, 3), jnp.float32),
        proprio=jnp.zeros((starts, rl.proprio_dim), jnp.float32),
        instruction_tokens=jnp.asarray(tokenize_instructions(["pick up the black bowl on the plate"] * starts,
                                                             rl.policy.max_instruction_bytes)),
        latents=jax.random.normal(jax.random.key(1), (starts, 2, hl, hl, vae.z_dim), jnp.float32),
    )
    start = jax.tree.map(lambda x: jax.device_put(x, shd.batch_sharding(mesh, x.ndim)), expand_groups(start, group))
    cfg = dataclasses.replace(rl, success_threshold=1.0,  # never stop early
                              grpo=dataclasses.replace(rl.grpo, group_size=group),
                              imagined=dataclasses.replace(rl.imagined, max_chunks=chunks,
                                                           sim_microbatches=sim_microbatches))

    @jax.jit
    def rollout(policy_params, sim, reward_model, start, key):
        out = imagined_rollout(policy_graphdef, policy_params, sim, reward_model, start, cfg, key=key)
        return out.returns, out.scores

    with shd.use_mesh(mesh):
        t0 = time.perf_counter()
        common.block(rollout(policy_params, sim, reward_model, start, jax.random.key(0)))
        compile_s = time.perf_counter() - t0
        timing = common.time_fn(lambda: rollout(policy_params, sim, reward_model, start, jax.random.key(1)),
                                warmup=1, iters=iters)
    frames = n * chunks * sim.chunk_len
    fps = frames / timing["median_s"] / jax.device_count()
    # One imagined frame: the whole rollout's matmul and convolution FLOPs counted on its jaxpr (policy, DiT
    # sampler steps, decode, reward CNN), and the decoder's share from one streamed 2-latent chunk.
    flops = common.jaxpr_flops(lambda *a: rollout(*a), policy_params, sim, reward_model, start,
                               jax.random.key(1)) / frames
    dit_flops = sample_steps * forward_flops(dit, 1, 4, (hl, hl), 13) / sim.chunk_len
    # The decoders as the simulator runs them (the precision's dtype and upsampling form); the VAE decoder's count
    # is taken with a light decoder too, for the ratio.
    vae_graphdef, vae_state = inference_vae(vae_graphdef, vae_state, precision)
    vae_cache = jax.eval_shape(lambda s: vae_api.init_decode_cache(vae_graphdef, s, 1, hl, hl), vae_state)
    vae_decode_flops = _decode_flops_per_frame(vae_graphdef, vae_state, start.latents[:1], vae_cache, light_form=False)
    decode_flops = vae_decode_flops
    if light_decoder is not None:
        light_graphdef = inference_light_decoder(*light_decoder, precision)[0]
        light_cache = jax.eval_shape(lambda s: light.init_stream_cache(light_graphdef, s, 1, hl, hl), decoder_state)
        decode_flops = _decode_flops_per_frame(light_graphdef, decoder_state, start.latents[:1], light_cache,
                                               light_form=True)
    upsample = "subpixel" if precision == "fast" else "repeat"
    return {"case": name, "precision": precision, "vae_form": f"{vae.causal_conv}/{upsample}",
            "sim_microbatches": sim_microbatches, "decoder": decoder, "frame_size": sim.frame_size,
            "gflop_per_frame": flops / 1e9, "dit_gflop_per_frame": dit_flops / 1e9,
            "decode_gflop_per_frame": decode_flops / 1e9, "vae_decode_gflop_per_frame": vae_decode_flops / 1e9,
            "ceiling_frames_per_s": peak_tflops * 1e12 / flops if peak_tflops else None,
            # the model's FLOPs per frame (attention counted) at the measured rate, against both peaks
            "mfu_measured_peak": common.mfu(flops, fps, peak_tflops),
            "mfu_nominal_peak": common.mfu(flops, fps, common.nominal_peak_tflops()),
            "weight_gb": parameter_bytes(wm_state) / 1e9,
            "frames_per_s_per_device": fps, "trajectories": n, "chunks": chunks, "frames": frames,
            "rollout_s": timing["median_s"], "compile_s": compile_s, "build_s": build_s, "dit_dim": dit.dim,
            "dit_layers": dit.num_layers, "resolution": frame_size, "sample_steps": sample_steps,
            "peak_gb": common.peak_memory_gb()}


def main(argv=None) -> None:
    parser = cli.ArgumentParser(description=__doc__)
    parser.add_argument("--tiny", action="store_true", help="CPU smoke run with tiny shapes (no results merged)")
    parser.add_argument("--layers", type=int, default=4, help="DiT blocks at 5B width (memory / time knob)")
    parser.add_argument("--starts", type=int, default=4)
    parser.add_argument("--group", type=int, default=8)
    parser.add_argument("--chunks", type=int, default=4)
    parser.add_argument("--sample-steps", type=int, default=5)
    parser.add_argument("--iters", type=int, default=3)
    parser.add_argument("--precision", choices=(*PRECISIONS, "both"), default="fast",
                        help="the simulator's rl.imagined.sim_precision, or fast and float32 side by side")
    parser.add_argument("--causal-conv", default="conv3d", choices=("conv3d", "conv2d"),
                        help="the VAE's causal-convolution form (bench_vae)")
    parser.add_argument("--decoder", choices=("full", "light"), default="full",
                        help="rl.imagined.decoder: the VAE's decoder, or the light decoder at rl.image_size")
    parser.add_argument("--skip-small", action="store_true", help="only the 5B-width case")
    parser.add_argument("--sim-microbatches", default="0",
                        help="comma-separated rl.imagined.sim_microbatches values for the 5B case, side by side "
                             "(0: the simulator's choice, as GRPO's default)")
    args = parser.parse_args(argv)
    modes = list(PRECISIONS) if args.precision == "both" else [args.precision]
    peak = common.measured_matmul_tflops()
    print(f"{common.device_name()}: measured bf16 matmul peak {peak:.1f} TFLOP/s")
    rows = []

    def attempt(*a, **kw):
        try:
            rows.append(run_case(*a, **kw, peak_tflops=peak))
        except Exception as err:  # noqa: BLE001 - out of memory: report it, keep the other cases
            if not common.is_oom(err):
                raise
            print(f"{a[0]} precision={kw.get('precision')}: out of memory ({str(err).splitlines()[0][:160]})")

    if args.tiny:
        tiny = configs.get("sword:tiny")
        rl = RLConfig(image_size=16, action_bins=16, policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=48),
                      reward_model=RewardModelConfig(width=4))
        for mode in modes:
            attempt("tiny", dataclasses.replace(tiny.model, compute_dtype="bfloat16"),
                    dataclasses.replace(tiny.vae, causal_conv=args.causal_conv), 32,
                    starts=1, group=2, chunks=2, sample_steps=2, rl=rl, iters=1, precision=mode, decoder=args.decoder)
    else:
        small = configs.get("sword:small")
        rl = RLConfig()
        for mode in [] if args.skip_small else modes:
            attempt("small", dataclasses.replace(small.model, compute_dtype="bfloat16"),
                    dataclasses.replace(small.vae, causal_conv=args.causal_conv), 128,
                    starts=args.starts, group=args.group, chunks=args.chunks,
                    sample_steps=args.sample_steps, rl=rl, iters=args.iters, precision=mode, decoder=args.decoder)
        dit5b = dataclasses.replace(DiTConfig(), num_layers=args.layers, compute_dtype="bfloat16")
        vae = dataclasses.replace(VAEConfig(), causal_conv=args.causal_conv)
        for mode in modes:
            for slices in (int(v) for v in args.sim_microbatches.split(",")):
                attempt("5b_width", dit5b, vae, 256, starts=args.starts, group=args.group, chunks=args.chunks,
                        sample_steps=args.sample_steps, rl=rl, iters=args.iters, precision=mode,
                        sim_microbatches=slices, decoder=args.decoder)
    common.print_table(rows, ["case", "precision", "decoder", "vae_form", "sim_microbatches", "weight_gb",
                              "frames_per_s_per_device", "trajectories", "chunks", "rollout_s", "compile_s",
                              "dit_layers", "resolution", "frame_size", "sample_steps", "gflop_per_frame",
                              "decode_gflop_per_frame", "vae_decode_gflop_per_frame", "ceiling_frames_per_s",
                              "mfu_measured_peak", "mfu_nominal_peak", "peak_gb"])
    if not args.tiny:
        # The headline: the fast path (GRPO's default) unless only float32 ran, or whichever ran when the other
        # ran out of memory.
        keep = "fast" if args.precision == "both" else args.precision

        def fastest(candidates):  # per case, the fastest row (of the sim_microbatches tried)
            best = {}
            for r in sorted(candidates, key=lambda r: r["frames_per_s_per_device"]):
                best[r["case"]] = r
            return best

        by_case = fastest(r for r in rows if r["precision"] == keep)
        if "5b_width" not in by_case:
            by_case = fastest(rows)
            keep = by_case["5b_width"]["precision"] if "5b_width" in by_case else keep
        if "5b_width" not in by_case:
            raise SystemExit("bench_imagined_rollout: no 5B-width case ran; nothing recorded")
        wide = by_case["5b_width"]
        full = args.layers == DiTConfig().num_layers
        decoding = ("full Wan 2.2 VAE streaming decode, 256x256" if args.decoder == "full" else
                    f"light decoder streaming decode at {wide['frame_size']}x{wide['frame_size']} (latents of 256x256)")
        note = (f"policy + DiT dim 3072 x {args.layers} layers (of 30) with a {args.sample_steps}-step sampler + "
                f"{decoding} + reward CNN, B*G={wide['trajectories']}, GRPO's simulator builder at precision {keep}")
        key = "imagined_frames_per_s_5b_full" if full else "imagined_frames_per_s_5b_width"
        entries = {key: common.record(
            key, wide["frames_per_s_per_device"], TARGET_5B_LIGHT if args.decoder == "light" else TARGET_5B,
            note=note, precision=keep, measured_peak_tflops=peak,
            **{k: wide[k] for k in ("vae_form", "sim_microbatches", "gflop_per_frame", "dit_gflop_per_frame", "decode_gflop_per_frame",
                                    "ceiling_frames_per_s", "peak_gb", "trajectories", "mfu_measured_peak",
                                    "mfu_nominal_peak")},
            nominal_peak_tflops=common.nominal_peak_tflops(),
            rows=rows)}
        if "small" in by_case:
            entries["imagined_frames_per_s_small"] = common.record(
                "imagined_frames_per_s_small", by_case["small"]["frames_per_s_per_device"], None,
                note="sword:small DiT/VAE, 128x128", precision=keep)
        fast = fastest(r for r in rows if r["precision"] == "fast")
        slow = fastest(r for r in rows if r["precision"] == "float32")
        if args.decoder == "light":  # the light decoder's figures beside (not over) the VAE decoder's
            entries = {f"{k}_light_decoder": v for k, v in entries.items()}
            entries["rollout_decode_gflop_per_frame"] = common.record(
                "rollout_decode_gflop_per_frame", wide["decode_gflop_per_frame"],
                wide["vae_decode_gflop_per_frame"] / 10,
                note=f"light decoder at {wide['frame_size']} px vs the Wan 2.2 VAE decoder at 256 px, one streamed "
                     f"chunk counted on its jaxpr, precision {keep}; target a tenth of the VAE decoder's",
                vae_decode_gflop_per_frame=wide["vae_decode_gflop_per_frame"])
        if args.precision == "both" and "5b_width" in fast and "5b_width" in slow:
            a, b = fast["5b_width"], slow["5b_width"]
            entries["imagined_rollout_fast_over_float32"] = common.record(
                "imagined_rollout_fast_over_float32", a["frames_per_s_per_device"] / b["frames_per_s_per_device"],
                None, note=note, value_is="frames/s of the simulator at precision fast / at float32",
                weight_gb={"fast": a["weight_gb"], "float32": b["weight_gb"]},
                peak_gb={"fast": a["peak_gb"], "float32_after_fast": b["peak_gb"]},
                small_ratio=(fast["small"]["frames_per_s_per_device"] / slow["small"]["frames_per_s_per_device"]
                             if "small" in fast and "small" in slow else None))
        print("merged into", common.merge_results(entries))


if __name__ == "__main__":
    cli.run(main)
