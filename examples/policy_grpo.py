"""Plug your own JAX policy into the learned simulator and post-train it with a few GRPO steps.

    python examples/policy_grpo.py --run RUN [--steps 3]

RUN: a ``python -m train.pipeline`` work dir (or a world-model work dir / checkpoint); without it
a tiny model is trained first (``_tiny_run.py``). The policy below is written here, not taken from
sword-jax: any ``nnx.Module`` mapping ``(frames [N, s, s, 3] in [0, 1], instruction tokens
[N, L], proprio [N, P], proprio_valid [N])`` to logits ``[N, chunk_len, action_dim, bins]`` over
``bins`` action bins in [-1, 1] fits :func:`sword_jax.rl.grpo.make_grpo_step`. So does the
reward: a function of the imagined frames with values in [0, 1] (here "light on the right side
of the picture"; a pipeline run also has its trained success detector, ``model.reward_model``).
A shaped reward like this one is paid as its summed change per chunk (``rl.imagined.return_rule="score"``);
the default return, ``"success"``, pays only reaching the success threshold. Each GRPO step rolls
``rl.grpo.rollout_batch x rl.grpo.group_size`` trajectories out inside the world model
(one jit: policy, world model, VAE decoder, reward) and updates the policy from the
group-normalised returns.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import optax
from flax import nnx

import sword_jax
from _tiny_run import tiny_run
from sword_jax.rl import grpo
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, RLConfig
from sword_jax.rl.learned_simulator import RewardModel


class MyPolicy(nnx.Module):
    """A deliberately small policy: a strided conv over the frame, the mean of the instruction's
    byte embeddings, one linear layer to every action token's logits."""

    def __init__(self, cfg: RLConfig, *, rngs: nnx.Rngs):
        self.conv = nnx.Conv(3, 16, (4, 4), strides=(4, 4), rngs=rngs)
        self.words = nnx.Embed(257, 16, rngs=rngs)  # byte tokens: 0 = padding, b + 1 = byte b
        self.head = nnx.Linear(32, cfg.chunk_len * cfg.action_dim * cfg.action_bins, rngs=rngs)
        self.logit_shape = (cfg.chunk_len, cfg.action_dim, cfg.action_bins)

    def __call__(self, frames, instruction_tokens, proprio, proprio_valid):
        del proprio, proprio_valid  # the world model reports no proprio (valid = 0)
        seen = jnp.mean(jax.nn.gelu(self.conv(frames)), axis=(1, 2))  # (N, 16)
        mask = (instruction_tokens > 0)[..., None].astype(jnp.float32)
        said = jnp.sum(self.words(instruction_tokens) * mask, axis=1) / jnp.maximum(jnp.sum(mask, axis=1), 1.0)
        return self.head(jnp.concatenate([seen, said], axis=-1)).reshape((-1,) + self.logit_shape)


def light_on_the_right(frames):
    """Success score in [0, 1] of frames [n, H, W, 3]: the right half brighter than the left."""
    half = frames.shape[2] // 2
    contrast = jnp.mean(frames[:, :, half:], axis=(1, 2, 3)) - jnp.mean(frames[:, :, :half], axis=(1, 2, 3))
    return jax.nn.sigmoid(20.0 * contrast)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", help="trained run (default: train a tiny one)")
    parser.add_argument("--workdir", default="runs/examples-tiny", help="where the tiny run goes")
    parser.add_argument("--train-steps", type=int, default=10, help="steps of the tiny run")
    parser.add_argument("--steps", type=int, default=3, help="GRPO steps")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    model = sword_jax.load_world_model(tiny_run(args.run, workdir=args.workdir, steps=args.train_steps))
    spec = model.spec
    rl = RLConfig(chunk_len=spec.frames_per_chunk, action_dim=spec.action_dim, image_size=spec.image_size,
                  grpo=GRPOConfig(steps=args.steps, rollout_batch=2, group_size=4, learning_rate=1e-3),
                  imagined=ImaginedConfig(max_chunks=2, return_rule="score"))
    graphdef, params = nnx.split(MyPolicy(rl, rngs=nnx.Rngs(args.seed)))

    from sword_jax.vae.train import moving_squares  # start frames: what the tiny VAE saw

    keyframes = (moving_squares(key=jax.random.key(args.seed), batch=rl.grpo.rollout_batch, frames=1,
                                size=spec.image_size)[:, 0] + 1.0) / 2.0
    starts = sword_jax.start_states(model, keyframes, ["move the light to the right"] * rl.grpo.rollout_batch,
                                    max_instruction_bytes=rl.policy.max_instruction_bytes)
    simulator = sword_jax.learned_simulator(model)
    reward = RewardModel(params=None, score_fn=lambda _, frames: light_on_the_right(frames))

    step = grpo.make_grpo_step(graphdef, rl)  # step(state, (simulator, reward, starts), key); state donated
    state = grpo.init_state(params, rl)
    start_params = jax.tree.map(jnp.copy, state.params)
    history = []
    for i in range(args.steps):
        state, metrics = step(state, (simulator, reward, starts), jax.random.key(args.seed))
        metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
        history.append(metrics)
        print(f"grpo step {i + 1}/{args.steps}: imagined success {metrics['success_rate']:.2f} return "
              f"{metrics['mean_return']:.3f} loss {metrics['loss']:.4f} kept groups {metrics['kept_fraction']:.2f}")
    moved = float(optax.global_norm(jax.tree.map(lambda a, b: a - b, state.params, start_params)))
    print(f"policy parameters moved by {moved:.4g} (global norm) in {args.steps} GRPO steps")
    return {"history": history, "moved": moved}


if __name__ == "__main__":
    main()
