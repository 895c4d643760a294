"""The learned simulator as an environment: a brax ``Env`` and gymnasium wrappers.

* :class:`ImaginedEnv` — pure ``reset(start, key) -> State`` / ``step(state, action_chunk) -> State``
  for ONE environment; ``State`` is brax's ``envs.State``. Its ``pipeline_state``
  (:class:`ImaginedPipelineState`) holds the simulator state and the episode's progress (last
  score, chunks taken, success run), so brax's ``AutoResetWrapper``, which restores
  ``pipeline_state`` and ``obs``, restarts an episode whole. ``jax.vmap`` batches it, auto-reset and
  episode limits stay outside ``step`` (brax / mujoco_playground convention, except that the chunk
  limit is part of the task and reported as ``info['truncation']``).
* :class:`ImaginedPoolEnv` — a brax ``Env`` over a pool of start states: pure ``reset(rng) -> State``
  (a start drawn from the pool by ``rng``) and ``step(state, action)``, ``action_size`` /
  ``observation_size`` / ``backend`` as brax defines them, so brax's training wrappers
  (``brax.envs.wrappers.training.wrap``) and trainers (``brax.training.agents.ppo``) take it.
* :class:`ImaginedVectorEnv` — a ``gymnasium.vector.VectorEnv`` over a pool of start states
  (dataset keyframes + instructions), next-step auto-reset, numpy in / numpy out.
* :class:`ImaginedGymEnv` — the single-env ``gymnasium.Env`` (what ``check_env`` checks).

An action is one chunk ``[chunk_len, action_dim]`` in [-1, 1] (flat ``[chunk_len * action_dim]`` for
brax's trainers). Observations are a dict: the frame under ``pixels/frame`` (the ``pixels/`` keys brax's
vision PPO runs its CNN on; the gymnasium envs call it ``frame``), ``proprio``, ``proprio_valid`` (``[1]``,
as brax's observation normalizer wants every other leaf a vector; a scalar in the gymnasium envs),
``instruction_tokens``. Every frame is at the simulator's ``frame_size`` (the start frame resized to it, as
for GRPO's policy: a light decoder's frames may be smaller than the start states'). A step returns the last
predicted frame as the observation, all predicted frames in ``info['frames']``, the change of the success
score as reward, ``terminated`` on success (score >= threshold) and ``truncated`` at the chunk limit: the
rule of the GRPO rollouts, :func:`sword_jax.rl.rollout.chunk_outcome`. An episode's summed rewards are the
GRPO return of ``rl.imagined.return_rule=score`` without its ``rl.grpo.success_bonus`` (the default GRPO
return, ``success``, pays success alone).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State
from flax import struct
from gymnasium.vector import AutoresetMode

from sword_jax.rl.learned_simulator import LearnedSimulator, RewardModel, StartState
from sword_jax.rl.policy import resize_frames
from sword_jax.rl.rollout import chunk_outcome


FRAME_KEY = "pixels/frame"  # brax's vision networks run their CNN on the observation keys starting "pixels/"


@struct.dataclass
class ImaginedPipelineState:
    """What an episode restarts from: the simulator state and the episode's progress so far.

    Attributes:
      simulator: the learned simulator's state.
      score: () the success score of the last frame (the next reward's baseline).
      chunk: () int32 action chunks taken.
      run: () int32 consecutive success frames at the end of the last chunk.
    """

    simulator: Any
    score: jax.Array
    chunk: jax.Array
    run: jax.Array


@struct.dataclass
class ImaginedEnv:
    """Functional env over a learned simulator and a reward model (one environment)."""

    simulator: LearnedSimulator
    reward_model: RewardModel
    success_threshold: float = struct.field(pytree_node=False, default=0.9)
    max_chunks: int = struct.field(pytree_node=False, default=8)
    success_frames: int = struct.field(pytree_node=False, default=1)  # consecutive success frames a success needs

    def _obs(self, sim_state, frame, tokens):
        proprio, valid = self.simulator.observe(sim_state)
        return {FRAME_KEY: frame, "proprio": proprio.astype(jnp.float32),
                "proprio_valid": jnp.reshape(valid, (1,)).astype(jnp.float32),  # brax's obs leaves are vectors
                "instruction_tokens": tokens}

    def reset(self, start: StartState, *, key: jax.Array) -> State:
        """Starts from one keyframe/instruction; ``key`` seeds the simulator's noise. The observed frame is the
        start frame at the simulator's ``frame_size``; the score is the start frame's, as in GRPO's rollouts."""
        sim_state = self.simulator.init(start)
        score = self.reward_model.score(start.frame[None])[0]
        frame = resize_frames(start.frame, self.simulator.frame_size)  # (S, S, 3)
        t = self.simulator.frames_per_step
        pipeline_state = ImaginedPipelineState(sim_state, score, jnp.zeros((), jnp.int32), jnp.zeros((), jnp.int32))
        info = {"key": key, "score": score, "truncation": jnp.zeros((), jnp.float32),
                "success": jnp.zeros((), jnp.float32), "frames": jnp.zeros((t,) + frame.shape, jnp.float32)}
        return State(pipeline_state, self._obs(sim_state, frame, start.instruction_tokens),
                     jnp.zeros((), jnp.float32), jnp.zeros((), jnp.float32), {"score": score}, info)

    def step(self, state: State, action_chunk: jax.Array) -> State:
        """Advances one action chunk ``[chunk_len, action_dim]``; a done env is left unchanged."""
        key, step_key = jax.random.split(state.info["key"])
        progress = state.pipeline_state
        actions = jnp.clip(action_chunk.astype(jnp.float32), -1.0, 1.0)
        sim_state, frames = self.simulator.step(progress.simulator, actions, key=step_key)
        scores = self.reward_model.score(frames)
        was_done = state.done > 0
        outcome = chunk_outcome(scores, progress.score, was_done, progress.chunk,
                                success_threshold=self.success_threshold, max_chunks=self.max_chunks,
                                prev_run=progress.run, success_frames=self.success_frames)
        success, truncation = outcome.success.astype(jnp.float32), outcome.truncated.astype(jnp.float32)
        new = State(
            ImaginedPipelineState(sim_state, outcome.score, progress.chunk + 1, outcome.run),
            self._obs(sim_state, frames[-1].astype(jnp.float32), state.obs["instruction_tokens"]),
            outcome.reward, outcome.done.astype(jnp.float32), {"score": outcome.score},
            {**state.info, "key": key, "score": outcome.score, "truncation": truncation, "success": success,
             "frames": frames.astype(jnp.float32)},  # keys that wrappers added to info ride along
        )
        frozen = state.replace(reward=jnp.zeros((), jnp.float32))
        return jax.tree.map(lambda a, b: jnp.where(was_done, a, b), frozen, new)


@struct.dataclass
class ImaginedPoolEnv(Env):
    """brax ``Env``: ``reset(rng)`` starts from a start state drawn uniformly from ``pool``.

    One environment, pure and jittable. brax's training wrappers batch it, limit its episodes and
    reset them (``brax.envs.wrappers.training.wrap(env, episode_length=...)``, raw ``jax.random.PRNGKey`` keys
    as brax uses), or ``jax.vmap(env.reset)(keys)`` / ``jax.vmap(env.step)(states, actions)`` by hand.
    The env ends an episode itself after ``env.max_chunks`` chunks (``info['truncation']``, which
    brax's ``EpisodeWrapper`` rewrites to mark its own ``episode_length`` limit): with
    ``episode_length < max_chunks`` brax's limit comes first and its trainers see it as a truncation.
    brax's ``AutoResetWrapper`` restarts an episode from its own first state (not a new draw from the
    pool), the simulator's noise key running on.

    Attributes:
      env: the functional env (simulator, reward model, threshold, chunk limit).
      pool: start states with a leading pool axis ``[M, ...]`` (:class:`StartState`).
    """

    env: ImaginedEnv
    pool: StartState

    @property
    def pool_size(self) -> int:
        return int(self.pool.frame.shape[0])

    @property
    def observation_size(self) -> dict[str, tuple[int, ...]]:
        """Shapes of one observation's entries (brax's dict form; traced abstractly, nothing runs)."""
        obs = jax.eval_shape(lambda env: env.reset(jax.random.key(0)).obs, self)
        return {name: tuple(value.shape) for name, value in obs.items()}

    @property
    def action_size(self) -> int:
        """``chunk_len * action_dim``: one action is a whole chunk, flat as brax's trainers give it."""
        return self.env.simulator.chunk_len * self.env.simulator.action_dim

    @property
    def action_shape(self) -> tuple[int, int]:
        """``(chunk_len, action_dim)``: the chunk a flat action is reshaped to."""
        return self.env.simulator.chunk_len, self.env.simulator.action_dim

    @property
    def backend(self) -> str:
        return "learned_simulator"

    def reset(self, rng: jax.Array) -> State:
        """A new episode from ``pool[randint(rng)]``; the rest of ``rng`` seeds the simulator."""
        pick_key, env_key = jax.random.split(rng)
        index = jax.random.randint(pick_key, (), 0, self.pool_size)
        return self.env.reset(_index(self.pool, index), key=env_key)

    def step(self, state: State, action: jax.Array) -> State:
        """One action chunk, ``[chunk_len * action_dim]`` or ``[chunk_len, action_dim]`` (clipped to
        [-1, 1]); done episodes stay frozen."""
        if np.size(action) != self.action_size:
            raise ValueError(f"an action must hold {self.action_shape} = {self.action_size} values, got shape "
                             f"{np.shape(action)}")
        return self.env.step(state, jnp.reshape(action, self.action_shape))


def _index(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


# Compiled once per env structure (simulator functions, shapes), shared by every vector env built on it.
_batched_reset = jax.jit(jax.vmap(lambda env, start, key: env.reset(start, key=key), in_axes=(None, 0, 0)))
_batched_step = jax.jit(jax.vmap(lambda env, state, action: env.step(state, action), in_axes=(None, 0, 0)))
_select_envs = jax.jit(lambda mask, a, b: jax.tree.map(
    lambda x, y: jnp.where(mask.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), a, b))


class ImaginedVectorEnv(gym.vector.VectorEnv):
    """``gymnasium.vector.VectorEnv`` of ``num_envs`` imagined rollouts (next-step auto-reset).

    Args:
      env: the functional env.
      start_pool: start states with a leading pool axis ``[M, ...]``; each reset draws one per
        env from ``self.np_random`` (or takes ``options['start_index']``, an int array ``[num_envs]``).
      num_envs: environments stepped together (one jitted, vmapped call).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, env: ImaginedEnv, start_pool: StartState, num_envs: int):
        self.env, self.pool, self.num_envs = env, start_pool, int(num_envs)
        self.pool_size = int(start_pool.frame.shape[0])
        h = w = env.simulator.frame_size  # the frames observed (a light decoder's may be smaller than the pool's)
        p = start_pool.proprio.shape[-1]
        l = start_pool.instruction_tokens.shape[-1]
        t, a = env.simulator.chunk_len, env.simulator.action_dim
        self.single_observation_space = gym.spaces.Dict({
            "frame": gym.spaces.Box(0.0, 1.0, (h, w, 3), np.float32),
            "proprio": gym.spaces.Box(-np.inf, np.inf, (p,), np.float32),
            "proprio_valid": gym.spaces.Box(0.0, 1.0, (), np.float32),
            "instruction_tokens": gym.spaces.Box(0, 256, (l,), np.int32),
        })
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (t, a), np.float32)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self._reset_fn, self._step_fn, self._select = _batched_reset, _batched_step, _select_envs
        self._state: State | None = None
        self._needs_reset = np.zeros(self.num_envs, bool)

    def _draw(self, count: int, start_index=None) -> tuple[StartState, jax.Array]:
        if start_index is None:
            start_index = self.np_random.integers(0, self.pool_size, count)
        start_index = np.asarray(start_index, np.int64).reshape(count)
        if np.any(start_index < 0) or np.any(start_index >= self.pool_size):
            raise ValueError(f"start_index {start_index} outside the pool of {self.pool_size} start states")
        seeds = self.np_random.integers(0, 2**31 - 1, count)
        keys = jax.vmap(jax.random.key)(jnp.asarray(seeds, jnp.uint32))
        return _index(self.pool, jnp.asarray(start_index)), keys

    def _numpy_obs(self, state: State) -> dict[str, np.ndarray]:
        """The gymnasium layout of the brax observations: ``frame`` for ``pixels/frame``, ``proprio_valid``
        one number per env."""
        obs = jax.device_get(state.obs)
        obs["frame"] = obs.pop(FRAME_KEY)
        obs["proprio_valid"] = obs["proprio_valid"][..., 0]
        return {k: np.asarray(v, self.single_observation_space[k].dtype) for k, v in obs.items()}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        start, keys = self._draw(self.num_envs, (options or {}).get("start_index"))
        self._state = self._reset_fn(self.env, start, keys)
        self._needs_reset[:] = False
        return self._numpy_obs(self._state), {"score": np.asarray(self._state.info["score"])}

    def step(self, actions):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        actions = np.asarray(actions, np.float32)
        if actions.shape != self.action_space.shape:
            raise ValueError(f"actions must have shape {self.action_space.shape}, got {actions.shape}")
        if not np.all(np.isfinite(actions)):
            raise ValueError("actions contain NaN/inf")
        stepped = self._step_fn(self.env, self._state, jnp.asarray(actions))
        reward = np.asarray(stepped.reward, np.float32)
        terminated = np.asarray(stepped.info["success"] > 0)
        truncated = np.asarray(stepped.info["truncation"] > 0)
        if self._needs_reset.any():  # next-step auto-reset: these envs ignore the action
            start, keys = self._draw(self.num_envs)
            fresh = self._reset_fn(self.env, start, keys)
            mask = jnp.asarray(self._needs_reset)
            stepped = self._select(mask, fresh, stepped)
            reward = np.where(self._needs_reset, 0.0, reward).astype(np.float32)
            terminated = np.where(self._needs_reset, False, terminated)
            truncated = np.where(self._needs_reset, False, truncated)
        self._state = stepped
        self._needs_reset = terminated | truncated
        info = {"frames": np.asarray(stepped.info["frames"]), "score": np.asarray(stepped.info["score"])}
        return self._numpy_obs(stepped), reward, terminated, truncated, info


class ImaginedGymEnv(gym.Env):
    """Single ``gymnasium.Env`` view of :class:`ImaginedVectorEnv` (``num_envs = 1``)."""

    metadata = {"render_modes": []}

    def __init__(self, env: ImaginedEnv, start_pool: StartState):
        self._vec = ImaginedVectorEnv(env, start_pool, 1)
        self.observation_space = self._vec.single_observation_space
        self.action_space = self._vec.single_action_space

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None or self._vec._np_random is None:
            self._vec._np_random, _ = gym.utils.seeding.np_random(int(self.np_random.integers(0, 2**31 - 1)))
        self._vec._state = None
        start, keys = self._vec._draw(1, (options or {}).get("start_index"))
        self._vec._state = self._vec._reset_fn(self._vec.env, start, keys)
        obs = {k: np.asarray(v[0]) for k, v in self._vec._numpy_obs(self._vec._state).items()}
        return obs, {"score": float(self._vec._state.info["score"][0])}

    def step(self, action):
        if self._vec._state is None:
            raise RuntimeError("call reset() before step()")
        obs, reward, terminated, truncated, info = self._vec.step(np.asarray(action, np.float32)[None])
        self._vec._needs_reset[:] = False  # a single env is reset by its caller
        return ({k: np.asarray(v[0]) for k, v in obs.items()}, float(reward[0]), bool(terminated[0]), bool(truncated[0]),
                {"frames": info["frames"][0], "score": float(info["score"][0])})
