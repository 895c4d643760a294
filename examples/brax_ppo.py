"""One brax PPO call, trained against the ground-truth MJX env or inside the learned simulator: swap the env.

    python examples/brax_ppo.py --env learned [--run RUN]      # inside a world model
    python examples/brax_ppo.py --env mjx [--resolution 64]    # MuJoCo physics on MJX, ray-cast camera frames
    python examples/brax_ppo.py --env toy                      # the learned simulator's env over a toy world

Both envs are brax ``Env``s (``sim.mjx_env.MjxEnv`` and ``sword_jax.rl.env.ImaginedPoolEnv``) whose dict
observations hold camera frames under ``pixels/...`` and proprioception under ``proprio``, the layout
brax's vision PPO reads, so :func:`train` hands either, unchanged, to ``brax.training.agents.ppo.train``
(brax's own training wrappers batch it, limit and auto-reset its episodes). It prints each iteration's
env steps per second (brax's ``training/sps``; the first iteration includes compilation).

``learned``: RUN as in ``policy_grpo.py`` (a pipeline work dir; without it a tiny model is trained first),
its start frames the tiny VAE's moving squares and its reward the change of a score of the frames (the
run's success detector where it has one, else "light on the right"). An action is one flat chunk of
``4p x a`` actions. ``mjx``: LIBERO-Spatial task ``--task``, reward 1 on success, 7-D actions; MJX
compiles for minutes and steps slowly on a CPU, so run it on a GPU. ``toy``: the learned simulator's env
over ``sword_jax.rl.learned_simulator.toy_simulator`` (an analytic point-reaching world, no model to
load: seconds on a CPU).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np


def learned_env(run: str | None, *, workdir: str, train_steps: int, episode_length: int, seed: int):
    """The learned simulator's brax env over a trained world model (``--env learned``)."""
    import sword_jax
    from _tiny_run import tiny_run
    from policy_grpo import light_on_the_right
    from sword_jax.vae.train import moving_squares

    model = sword_jax.load_world_model(tiny_run(run, workdir=workdir, steps=train_steps))
    size = model.spec.image_size
    keyframes = (moving_squares(key=jax.random.key(seed), batch=4, frames=1, size=size)[:, 0] + 1.0) / 2.0
    pool = sword_jax.start_states(model, keyframes, ["move the light to the right"] * 4)
    reward_model = light_on_the_right if model.reward_model is None else model.reward_model
    # episode_length < max_chunks: brax's EpisodeWrapper ends episodes first and marks them truncated
    return sword_jax.make_env(model, pool, reward_model=reward_model, max_chunks=episode_length + 1)


def toy_env(*, frame_size: int, chunk_len: int, episode_length: int, seed: int):
    """The learned simulator's brax env over the analytic toy world (``--env toy``)."""
    from sword_jax.rl.env import ImaginedEnv, ImaginedPoolEnv
    from sword_jax.rl.learned_simulator import toy_reward_model, toy_simulator, toy_start_states
    from sword_jax.rl.policy import tokenize_instructions

    tokens = jnp.asarray(tokenize_instructions(["reach the left goal", "reach the right goal"], 16))
    pool = toy_start_states(tokens, key=jax.random.key(seed), frame_size=frame_size)
    simulator = toy_simulator(frame_size=frame_size, chunk_len=chunk_len, noise=0.01)
    return ImaginedPoolEnv(ImaginedEnv(simulator, toy_reward_model(), max_chunks=episode_length + 1), pool)


def mjx_env(*, task: int, resolution: int):
    """The ground-truth MJX env with the agentview camera as ``pixels/agentview_rgb`` (``--env mjx``)."""
    import sim
    from sim.env import camera_renderer

    renderer = camera_renderer(sim.load("libero_spatial").mj_model, resolution=resolution, pixels=True)
    return sim.load("libero_spatial", task_id=task, backend="mjx", renderer=renderer)


@contextlib.contextmanager
def _device_put_replicated():
    """brax 0.14.2's PPO replicates its train state with ``jax.device_put_replicated``, which jax 0.10
    removed (google/brax#671). For the duration of the call this puts back the drop-in replacement JAX's
    pmap migration guide gives; on a jax that still has it, nothing changes."""
    if hasattr(jax, "device_put_replicated"):
        yield
        return
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    def device_put_replicated(tree, devices):
        # on the mesh axis of brax's pmap ("i"), where its epochs leave the state: the first epoch then
        # compiles for the same input shardings as the others, once
        sharding = NamedSharding(Mesh(np.array(devices), ("i",)), PartitionSpec("i"))
        return jax.tree.map(lambda x: jax.device_put(jnp.stack([x] * len(devices)), sharding), tree)

    jax.device_put_replicated = device_put_replicated
    try:
        yield
    finally:
        del jax.device_put_replicated


def train(env, *, num_envs: int, unroll_length: int, iterations: int, episode_length: int, seed: int = 0,
          hidden: int = 256, cnn_channels: tuple[int, ...] = (32, 64, 64)) -> dict:
    """brax's PPO with its vision networks on ``env``, ``iterations`` training epochs of one step each.

    Returns:
      ``{"iterations": [{"env_steps", "steps_per_s", "policy_loss"}, ...], "seconds": s}``: each epoch's
      env steps so far and brax's ``training/sps`` (the first epoch's includes compilation).
    """
    from brax.training.agents.ppo import networks_vision
    from brax.training.agents.ppo import train as ppo

    kernels, strides = (8, 4, 3)[-len(cnn_channels):], (4, 2, 1)[-len(cnn_channels):]
    network_factory = functools.partial(
        networks_vision.make_ppo_networks_vision, policy_obs_key="proprio", value_obs_key="proprio",
        policy_hidden_layer_sizes=(hidden, hidden), value_hidden_layer_sizes=(hidden, hidden),
        cnn_output_channels=cnn_channels, cnn_kernel_size=kernels, cnn_stride=strides)
    history = []

    def progress(step, metrics):
        history.append({"env_steps": int(step), "steps_per_s": float(metrics["training/sps"]),
                        "policy_loss": float(metrics["training/policy_loss"])})
        print(f"ppo iteration {len(history)}/{iterations}: {int(step)} env steps, "
              f"{history[-1]['steps_per_s']:.1f} env steps/s, policy loss {history[-1]['policy_loss']:.4f}", flush=True)

    start = time.perf_counter()
    with _device_put_replicated():
        ppo.train(env, num_timesteps=iterations * num_envs * unroll_length, episode_length=episode_length,
                  num_envs=num_envs, batch_size=num_envs, num_minibatches=1, unroll_length=unroll_length,
                  num_updates_per_batch=1, num_evals=iterations + 1, run_evals=False, vision=True,
                  network_factory=network_factory, learning_rate=3e-4, seed=seed, progress_fn=progress,
                  max_devices_per_host=1)
    return {"iterations": history, "seconds": time.perf_counter() - start}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", choices=("learned", "mjx", "toy"), default="learned")
    parser.add_argument("--run", help="--env learned: trained run (default: train a tiny one)")
    parser.add_argument("--workdir", default="runs/examples-tiny", help="where the tiny run goes")
    parser.add_argument("--train-steps", type=int, default=10, help="steps of the tiny run")
    parser.add_argument("--task", type=int, default=0, help="--env mjx: LIBERO-Spatial task")
    parser.add_argument("--resolution", type=int, default=64, help="--env mjx: camera frames' side")
    parser.add_argument("--num-envs", type=int, default=64)
    parser.add_argument("--unroll-length", type=int, default=4, help="env steps per env per PPO step")
    parser.add_argument("--iterations", type=int, default=3, help="PPO epochs (one training step each)")
    parser.add_argument("--episode-length", type=int, default=None,
                        help="env steps per episode (default: 220 for mjx, LIBERO's limit; else 8)")
    parser.add_argument("--hidden", type=int, default=256, help="width of the policy and value MLPs")
    parser.add_argument("--cnn-channels", default="32,64,64", help="channels of the CNN's layers (at most 3)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    episode_length = args.episode_length or (220 if args.env == "mjx" else 8)
    if args.env == "learned":
        env = learned_env(args.run, workdir=args.workdir, train_steps=args.train_steps, episode_length=episode_length,
                          seed=args.seed)
    elif args.env == "mjx":
        env = mjx_env(task=args.task, resolution=args.resolution)
    else:
        env = toy_env(frame_size=16, chunk_len=4, episode_length=episode_length, seed=args.seed)
    print(f"env {args.env} ({type(env).__name__}, backend {env.backend}): action_size {env.action_size}, "
          f"observations {env.observation_size}", flush=True)
    result = train(env, num_envs=args.num_envs, unroll_length=args.unroll_length, iterations=args.iterations,
                   episode_length=episode_length, seed=args.seed, hidden=args.hidden,
                   cnn_channels=tuple(int(c) for c in args.cnn_channels.split(",")))
    print(f"trained {args.iterations} PPO iterations in {result['seconds']:.1f} s; last iteration "
          f"{result['iterations'][-1]['steps_per_s']:.1f} env steps/s on {jax.devices()[0].platform}")
    return {"env": args.env, **result}


if __name__ == "__main__":
    main()
