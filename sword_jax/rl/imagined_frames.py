"""Episodes' frames as the learned world model imagines them: each episode's own actions replayed, open loop, from
its real frames at the start of every window.

In the world model's simulator the policy reads frames the world model imagined from its own actions, and its
actions there rarely succeed when executed in reality, even where the VAE's round trip alone costs it nothing
(``benchmarks.bench_sim_fidelity``). Decoder-aware SFT on these frames (``rl.sft.decoded_source=world_model``)
pairs each imagined frame with the demonstration's action at the same step: the action that is right in the real
state the imagined frame stands for. The policy learns to act on the simulator's frames as it would on the real
ones, which is what makes the real outcome of actions chosen in imagination follow the imagined one.

An episode is cut into windows of ``1 + window`` frames starting at frames ``0, w, 2 w, ...`` (``w = 1 + window``);
each window starts from the real frame there and the real history before it (:func:`~sword_jax.rl.data.keyframe_window`,
encoded as GRPO's keyframe starts are: with ``rl.imagined.start_encoding=prefix`` the episode from frame 0 to it)
and replays the window's actions through the simulator
(:func:`~sword_jax.rl.sim_agreement.replay_actions`). Frame ``t`` of the result is the real frame at a window's
start (and at every frame of an episode of one frame) and otherwise the frame the simulator showed after action
``t - 1``, so the imagined drift ranges over what a
rollout of ``window`` actions from a keyframe sees. Frames after an episode's length repeat its last frame, as an
``EpisodeSet``'s padding does.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sword_jax.rl import data as rl_data
from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel, StartState
from sword_jax.rl.policy import tokenize_instructions
from sword_jax.rl.sim_agreement import replay_actions

# the replay scores nothing: a reward model of zeros keeps replay_actions' frames and drops its scores
_NO_REWARD = RewardModel(params=(), score_fn=lambda params, frames: jnp.zeros(frames.shape[:1], jnp.float32))


def window_starts(lengths: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """``(episode, t0)``: every window's start, frames ``0, w, 2 w, ...`` (``w = 1 + window``: the real start frame
    and the ``window`` frames its replay shows) before each episode's last frame (``lengths`` frames each, frame
    ``t`` seen before action ``t``: a replay shows frames ``t0 + 1 ..``, so an episode of one frame has none)."""
    if window < 1:
        raise ValueError(f"window_starts: window must be >= 1, got {window}")
    lengths = np.asarray(lengths, np.int64)
    per = -(-np.maximum(lengths - 1, 0) // (window + 1))
    episode = np.repeat(np.arange(len(lengths)), per)
    t0 = np.concatenate([np.arange(n) * (window + 1) for n in per]) if len(per) else np.zeros(0, np.int64)
    return episode, t0.astype(np.int64)


def imagined_episode_frames(
    simulator: LearnedSimulator,
    encode: Callable[[Any, Any], Any],
    episodes: rl_data.EpisodeSet,
    *,
    window: int,
    key: jax.Array,
    num_context: int = 1,
    frames_per_latent: int = 4,
    max_instruction_bytes: int = 96,
    batch: int = 64,
    log: Callable[[str], object] | None = None,
    encode_prefix: Callable[[Any, Any], Any] | None = None,
) -> np.ndarray:
    """Every episode's frames with each window replayed through ``simulator`` (module docstring).

    Args:
      simulator: a learned simulator whose frames are ``episodes``' size (e.g. the world model's,
        :func:`sword_jax.rl.sim_builder.build_simulator`).
      encode: ``(first_frames [n, H, W, 3], history [n, 4 (k + 1), H, W, 3]) -> latents``, both in [0, 1]
        (:func:`sword_jax.rl.world_model_sim.encode_history` with the VAE bound), as GRPO's starts are encoded.
      episodes: ``frames [E, T, H, W, 3]`` uint8 (frame ``t`` seen before action ``t``), ``actions [E, T, A]``,
        ``proprio`` at the simulator's ``proprio_dim``, ``lengths`` frames each.
      window: actions replayed from each start (GRPO's imagined rollout: ``max_chunks x execute_steps``).
      key: the simulator's noise; window ``i`` of the run draws ``fold_in(key, i // batch)``'s.
      batch: windows replayed together (the last call is padded, so one program serves every call).
      log: progress lines, if given.
      encode_prefix: with ``rl.imagined.start_encoding=prefix``, ``(prefix [n, 1 + 4 S, H, W, 3] in [0, 1],
        latent_index [n]) -> latents`` (:func:`sword_jax.rl.world_model_sim.encode_prefix` with the VAE bound),
        used instead of ``encode``: each window's episode from frame 0 to its start
        (:func:`~sword_jax.rl.data.keyframe_window`'s ``prefix``; ``S`` one length for the call, the latest start's).

    Returns:
      ``[E, T, H, W, 3]`` uint8.
    """
    frames = np.asarray(episodes.frames)
    if frames.ndim != 5 or frames.dtype != np.uint8:
        raise ValueError(f"imagined_episode_frames: frames must be [E, T, H, W, 3] uint8, got {frames.shape} "
                         f"{frames.dtype}")
    if frames.shape[2:4] != (simulator.frame_size, simulator.frame_size):
        raise ValueError(f"imagined_episode_frames: the episodes' frames are {frames.shape[2:4]} but the simulator "
                         f"shows {simulator.frame_size} x {simulator.frame_size}; render them at the world model's "
                         "data.image_size")
    if n_empty := int(np.sum(np.asarray(episodes.lengths) < 1)):
        raise ValueError(f"imagined_episode_frames: {n_empty} episode(s) of no frames")
    if batch < 1:
        raise ValueError(f"imagined_episode_frames: batch must be >= 1, got {batch}")
    lengths = np.asarray(episodes.lengths, np.int64)
    ep, t0 = window_starts(lengths, window)
    n = len(ep)
    # each window's actions, [n, window, A] (past its episode's end: zeros, replayed but not kept)
    steps = t0[:, None] + np.arange(window)[None]
    actions = np.where((steps < lengths[ep, None])[..., None],
                       episodes.actions[ep[:, None], np.minimum(steps, frames.shape[1] - 1)], 0.0).astype(np.float32)
    keep = np.minimum(window, lengths[ep] - 1 - t0)  # the frames a window shows inside its episode
    if n == 0:
        return frames.copy()
    replay = jax.jit(lambda sim, start, acts, count, k: replay_actions(
        sim, _NO_REWARD, start, acts, count, success_threshold=1.0, key=k, record_frames=True).frames)
    # with the prefix: one length for every window, so the encoder compiles once
    prefix_latents = (None if encode_prefix is None else
                      int(max(np.max(-(-t0 // frames_per_latent)), num_context)))
    out = frames.copy()
    unit = lambda x: jnp.asarray(x, jnp.float32) / jnp.float32(255.0)  # noqa: E731
    started = time.time()
    for b, lo in enumerate(range(0, n, batch)):
        rows = np.arange(lo, lo + batch) % n  # the last call repeats windows to keep the shape
        pick = rl_data.keyframe_window(frames, episodes.actions, episodes.proprio, ep[rows], t0[rows],
                                       num_context=num_context, frames_per_latent=frames_per_latent,
                                       prefix_latents=prefix_latents)
        if encode_prefix is None:
            latents = encode(unit(pick["first_frame"]), unit(pick["history"]))
        else:
            latents = encode_prefix(unit(pick["prefix"]), jnp.asarray(pick["latent_index"], jnp.int32))
        start = StartState(unit(pick["frame"]), jnp.asarray(pick["proprio"], jnp.float32),
                           jnp.asarray(tokenize_instructions([episodes.instructions[e] for e in ep[rows]],
                                                             max_instruction_bytes)),
                           (latents, jnp.asarray(pick["actions"], jnp.float32)))
        imagined = np.asarray(jax.device_get(replay(simulator, start, jnp.asarray(actions[rows]),
                                                    jnp.asarray(keep[rows], jnp.int32), jax.random.fold_in(key, b))))
        for row in range(min(batch, n - lo)):
            i = lo + row
            e, s, count = ep[i], t0[i], keep[i]
            out[e, s + 1: s + 1 + count] = imagined[row, :count]
        if log is not None:
            done = min(lo + batch, n)
            log(f"imagined frames: {done}/{n} windows of {window} actions, eta "
                f"{(time.time() - started) / done * (n - done):.0f}s")
    for e, length in enumerate(lengths):  # the padding repeats the last frame, imagined or real
        out[e, length:] = out[e, length - 1]
    return out
