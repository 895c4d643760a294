"""The learned-simulator protocol the imagined rollouts run against, and a toy implementation.

A simulator is a pytree (:class:`LearnedSimulator`) holding its parameters as the only array
leaves and three pure functions as static fields, all for ONE trajectory (the rollout vmaps):

* ``init_fn(params, start: StartState) -> sim_state``
* ``step_fn(params, sim_state, action_chunk [T, A], key) -> (sim_state, frames [E, H, W, 3])``
  (``T = chunk_len`` actions in, the first ``E = frames_per_step`` of them executed)
* ``observe_fn(params, sim_state) -> (proprio [P], proprio_valid [])``

and optionally, for a whole batch, ``round_trip_fn(params, frames [n, S, S, 3]) -> frames [n, S, S, 3]``
(``S = frame_size``, in [0, 1]): a real frame as the simulator's decoder shows it when its latents are the real
scene's (the world model's VAE round trip), what :meth:`LearnedSimulator.round_trip` runs.

Passing the simulator as a jit *argument* keeps multi-GB world-model weights out of the
compiled program's constants. The world-model implementation lives in
:mod:`sword_jax.rl.world_model_sim`; :func:`toy_simulator` implements the same protocol with an
analytic point-reaching world for tests.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jaxtyping import Array, Float, Int


class StartState(NamedTuple):
    """Where an imagined rollout starts (one trajectory; batched along a leading axis elsewhere).

    Attributes:
      frame: the start frame (a dataset keyframe) ``[H, W, 3]`` float in [0, 1].
      proprio: proprioceptive state at the keyframe ``[P]``.
      instruction_tokens: byte tokens of the instruction ``[L]`` int32.
      latents: simulator-specific context (e.g. VAE latents of the keyframe's history) or an
        empty array when the simulator derives it from ``frame``.
    """

    frame: Float[Array, "h w 3"]
    proprio: Float[Array, " p"]
    instruction_tokens: Int[Array, " l"]
    latents: Any = ()


@struct.dataclass
class LearnedSimulator:
    """A functional simulator: ``params`` are traced leaves, the functions are static."""

    params: Any
    init_fn: Callable = struct.field(pytree_node=False)
    step_fn: Callable = struct.field(pytree_node=False)
    observe_fn: Callable = struct.field(pytree_node=False)
    chunk_len: int = struct.field(pytree_node=False, default=8)
    frame_size: int = struct.field(pytree_node=False, default=32)
    # actions executed (= frames returned) per step: the first ``execute_len`` of the chunk's
    # ``chunk_len``; the policy re-plans after them. None = the whole chunk.
    execute_len: int | None = struct.field(pytree_node=False, default=None)
    action_dim: int = struct.field(pytree_node=False, default=7)  # each action of a chunk [chunk_len, action_dim]
    # trajectories one simulator microbatch may hold (rl.imagined.sim_microbatches=0 chooses by it); None = no limit
    max_slice: int | None = struct.field(pytree_node=False, default=None)
    # frames -> the frames its decoder would show of them (the module docstring); None = the simulator has none
    round_trip_fn: Callable | None = struct.field(pytree_node=False, default=None)

    @property
    def frames_per_step(self) -> int:
        return self.chunk_len if self.execute_len is None else self.execute_len

    def init(self, start: StartState) -> Any:
        return self.init_fn(self.params, start)

    def step(self, sim_state: Any, action_chunk: Float[Array, "t a"], *, key: jax.Array):
        if action_chunk.shape[0] != self.chunk_len:
            raise ValueError(f"action chunk must have {self.chunk_len} actions, got shape {action_chunk.shape}")
        return self.step_fn(self.params, sim_state, action_chunk, key)

    def observe(self, sim_state: Any) -> tuple[Float[Array, " p"], Float[Array, ""]]:
        return self.observe_fn(self.params, sim_state)

    def round_trip(self, frames: Float[Array, "n h w 3"]) -> Float[Array, "n s s 3"]:
        """``frames [n, H, W, 3]`` in [0, 1] as the simulator's decoder shows them (``round_trip_fn``), at its
        ``frame_size`` (frames of another size are resized to it first), ``max_slice`` frames at a time."""
        if self.round_trip_fn is None:
            raise ValueError("this simulator has no round trip of real frames (round_trip_fn)")
        n, size = frames.shape[0], self.frame_size
        frames = frames.astype(jnp.float32)
        if frames.shape[1:3] != (size, size):
            frames = jax.image.resize(frames, (n, size, size, frames.shape[-1]), method="linear", antialias=True)
        per_slice = min(self.max_slice or n, n)
        if per_slice == n:
            return self.round_trip_fn(self.params, frames)
        slices = -(-n // per_slice)
        padded = jnp.concatenate([frames, jnp.repeat(frames[-1:], slices * per_slice - n, axis=0)])
        out = jax.lax.map(lambda some: self.round_trip_fn(self.params, some),
                          padded.reshape((slices, per_slice) + frames.shape[1:]))
        return out.reshape((slices * per_slice,) + out.shape[2:])[:n]


@struct.dataclass
class RewardModel:
    """Per-frame success score in [0, 1]: ``score_fn(params, frames [n, H, W, 3]) -> [n]``."""

    params: Any
    score_fn: Callable = struct.field(pytree_node=False)

    def score(self, frames: Float[Array, "n h w 3"]) -> Float[Array, " n"]:
        return self.score_fn(self.params, frames)


# ----------------------------------------------------------------------------- toy world


class ToyState(NamedTuple):
    position: Float[Array, " 2"]  # gripper xy in [-1, 1]
    target: Float[Array, " 2"]  # goal xy, a function of the instruction text


def instruction_target(tokens: Int[Array, " l"]) -> Float[Array, " 2"]:
    """A goal position that is a deterministic function of the instruction's bytes."""
    weights = jnp.arange(1, tokens.shape[-1] + 1, dtype=jnp.int32)
    h = jnp.sum(tokens.astype(jnp.int32) * weights) % 997
    angle = h.astype(jnp.float32) * jnp.float32(2.0 * jnp.pi / 997.0)
    return jnp.float32(0.6) * jnp.stack([jnp.cos(angle), jnp.sin(angle)])


def _render_blob(center: Float[Array, " 2"], size: int, width: float) -> Float[Array, "h w"]:
    grid = jnp.linspace(-1.0, 1.0, size, dtype=jnp.float32)
    yy, xx = jnp.meshgrid(grid, grid, indexing="ij")
    d2 = (xx - center[0]) ** 2 + (yy - center[1]) ** 2
    return jnp.exp(-d2 / jnp.float32(2.0 * width**2))


def toy_render(state: ToyState, size: int) -> Float[Array, "h w 3"]:
    """Red blob at the gripper, green blob at the target, blue constant background."""
    red = _render_blob(state.position, size, 0.15)
    green = _render_blob(state.target, size, 0.15)
    blue = jnp.full((size, size), 0.2, jnp.float32)
    return jnp.stack([red, green, blue], axis=-1)


def toy_simulator(
    *, frame_size: int = 16, chunk_len: int = 8, step_size: float = 0.08, noise: float = 0.0, proprio_dim: int = 4
) -> LearnedSimulator:
    """A point-reaching world: action dims 0-1 move the gripper; the goal comes from the text.

    Frames show the gripper (red) and the target (green); ``noise`` adds Gaussian jitter to the
    motion so that the ``key`` matters. Proprio is the gripper position padded to ``proprio_dim``. The reward depends on the action: only moving toward the
    text-specified target raises :func:`toy_reward_model`'s score.
    """

    def init_fn(params, start: StartState) -> ToyState:
        del params
        return ToyState(jnp.clip(start.proprio[:2].astype(jnp.float32), -1.0, 1.0), instruction_target(start.instruction_tokens))

    def step_fn(params, state: ToyState, chunk, key):
        del params
        jitter = jnp.float32(noise) * jax.random.normal(key, (chunk.shape[0], 2), jnp.float32)
        deltas = jnp.float32(step_size) * chunk[:, :2].astype(jnp.float32) + jitter
        positions = jnp.clip(state.position[None] + jnp.cumsum(deltas, axis=0), -1.0, 1.0)  # (T, 2)
        frames = jax.vmap(lambda p: toy_render(ToyState(p, state.target), frame_size))(positions)
        return ToyState(positions[-1], state.target), frames

    def observe_fn(params, state: ToyState):
        del params
        return jnp.concatenate([state.position, jnp.zeros((proprio_dim - 2,), jnp.float32)]), jnp.float32(1.0)

    return LearnedSimulator(params={}, init_fn=init_fn, step_fn=step_fn, observe_fn=observe_fn,
                            chunk_len=chunk_len, frame_size=frame_size)


def toy_reward_model(*, radius: float = 0.25) -> RewardModel:
    """Success score from the frames alone: overlap of the red and green blobs, in [0, 1]."""

    def score_fn(params, frames):
        del params
        red = frames[..., 0]
        green = frames[..., 1]
        overlap = jnp.sum(red * green, axis=(-2, -1)) / (jnp.sum(green * green, axis=(-2, -1)) + jnp.float32(1e-6))
        # overlap is exp(-d^2 / (4 w^2)) for two equal blobs; map distance `radius` to 0.9
        sharp = jnp.log(jnp.float32(0.9)) / jnp.log(jnp.float32(jnp.exp(-(radius**2) / (4 * 0.15**2))))
        return jnp.clip(overlap, 0.0, 1.0) ** sharp

    return RewardModel(params={}, score_fn=score_fn)


def toy_start_states(instruction_tokens: Int[Array, "n l"], *, key: jax.Array, frame_size: int = 16, proprio_dim: int = 4,
                     rows: np.ndarray | None = None) -> StartState:
    """Random start positions for the toy world, one per instruction row.

    ``rows``: make only these rows of the ``n`` (a process's share of a global batch); the positions are
    drawn for all ``n`` first, so each row is the same whichever rows are asked for.
    """
    n = instruction_tokens.shape[0]
    pos = jax.random.uniform(key, (n, 2), jnp.float32, -0.3, 0.3)
    if rows is not None:
        pos, instruction_tokens = pos[rows], instruction_tokens[rows]
        n = len(rows)
    targets = jax.vmap(instruction_target)(instruction_tokens)
    frames = jax.vmap(lambda p, t: toy_render(ToyState(p, t), frame_size))(pos, targets)
    proprio = jnp.concatenate([pos, jnp.zeros((n, proprio_dim - 2), jnp.float32)], axis=-1)
    return StartState(frames, proprio, instruction_tokens.astype(jnp.int32), jnp.zeros((n, 0), jnp.float32))
