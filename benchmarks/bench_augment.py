"""Style augmentation cost vs VAE encode vs the DiT train step: the per-step vs pre-encoded-copies decision.

    python -m benchmarks.bench_augment --tiny            # CPU, seconds
    python -m benchmarks.bench_augment --variant small   # one GPU
    python -m benchmarks.bench_augment --variant paper --flops-only   # any machine: XLA FLOP counts

Per training batch of the variant (``data.batch_size`` segments of ``1 + context + predict``
frames at ``data.image_size``) it reports:

* ``augment_ms``: measured time of the on-device augmentation of the batch;
* ``encode_ms``: measured time of ``vae.encode`` of the batch (random VAE weights: same cost);
* ``encode_gflop``: XLA's FLOP count of that encode (lowered abstractly, so exact at paper size);
* ``dit_step_gflop``: 6 x DiT params x latent tokens (forward + backward of the train step);
* ``encode_over_step``: the FLOP ratio; per-step augmentation would add this to every step;
* ``copies_gb``: host memory of the latent dataset with ``augment.styled_copies`` styled copies.
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

import configs
from benchmarks.common import merge_results, print_table, record, time_fn
from sword_jax import cli
from sword_jax.augment.style import sample_styles
from sword_jax.augment.synthetic import synthetic_episodes
from sword_jax.augment.transforms import augment_batch, to_signed_range


def dit_params(model_cfg) -> int:
    from sword_jax.dit.action_dit import WorldModel

    with nnx.use_eager_sharding(False):
        abstract = nnx.eval_shape(lambda: WorldModel(model_cfg, rngs=nnx.Rngs(0)))
    return int(sum(np.prod(x.shape) for x in jax.tree.leaves(nnx.state(abstract, nnx.Param))))


def encode_flops(vae_cfg, batch: int, frames: int, size: int) -> float:
    from sword_jax.vae import api

    graphdef, state = nnx.split(api.abstract_vae(vae_cfg))
    video = jax.ShapeDtypeStruct((batch, frames, size, size, 3), jnp.float32)
    lowered = jax.jit(lambda s, v: api.encode(graphdef, s, v, check_values=False)).lower(state, video)
    cost = lowered.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost["flops"])


def main(argv: list[str] | None = None) -> int:
    parser = cli.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tiny", action="store_true", help="the tiny variant on CPU")
    parser.add_argument("--variant", default="small", choices=("tiny", "small", "paper"))
    parser.add_argument("--flops-only", action="store_true", help="skip the timings (any machine, any size)")
    parser.add_argument("--iters", type=int, default=5)
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args(argv)
    variant = "tiny" if args.tiny else args.variant
    cfg = configs.get(f"sword:{variant}")
    data, vae_cfg, aug = cfg.data, cfg.vae, cfg.augment
    batch, size = data.batch_size, data.image_size
    frames = 1 + data.context_frames + data.predict_frames
    row = {"variant": variant, "batch": batch, "frames": frames, "size": size}

    patch = cfg.model.patch_size
    latent_frames = 1 + (frames - 1) // 4
    tokens = batch * latent_frames * (size // 16 // patch[1]) * (size // 16 // patch[2])
    row["dit_step_gflop"] = 6 * dit_params(cfg.model) * tokens / 1e9
    row["encode_gflop"] = encode_flops(vae_cfg, batch, frames, size) / 1e9
    row["encode_over_step"] = row["encode_gflop"] / row["dit_step_gflop"]
    episode_latents = (1 + (data.episode_frames - 1) // 4) * (size // 16) ** 2 * vae_cfg.z_dim * 4
    row["copies_gb"] = data.num_episodes * (1 + aug.styled_copies) * episode_latents / 1e9

    if not args.flops_only:
        from sword_jax.vae import api

        eps = synthetic_episodes(batch, frames, size)
        video, depth, seg = (jnp.asarray(eps[k]) for k in ("frames", "depth", "seg"))
        styles = sample_styles(jax.random.key(0), batch, "train")
        augment_fn = jax.jit(augment_batch)
        row["augment_ms"] = 1e3 * time_fn(lambda: augment_fn(video, depth, seg, styles), iters=args.iters)["median_s"]
        graphdef, state = nnx.split(api.create_vae(vae_cfg, key=jax.random.key(0)))
        signed = to_signed_range(video)
        encode = jax.jit(lambda s, v: api.encode(graphdef, s, v, check_values=False))
        row["encode_ms"] = 1e3 * time_fn(lambda: encode(state, signed), iters=args.iters)["median_s"]
        row["augment_over_encode"] = row["augment_ms"] / row["encode_ms"]

    print_table([row], list(row))
    if not args.no_record:
        prefix = f"augment.{variant}"
        names = {"encode_over_dit_step_flops": ("encode_over_step", "< 0.05 to prefer per-step augmentation"),
                 "encode_ms_per_batch": ("encode_ms", None), "augment_ms_per_batch": ("augment_ms", None)}
        extra = {k: v for k, v in row.items() if k not in ("variant",)}
        entries = {f"{prefix}.{name}": record(f"{prefix}.{name}", row[field], target, **extra)
                   for name, (field, target) in names.items() if field in row}
        merge_results(entries)
    return 0


if __name__ == "__main__":
    cli.run(main)
