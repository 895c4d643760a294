"""World-model training episodes in which a policy acts (successes and failures), recorded like the expert's.

Expert episodes are almost all successful (98% on `small`), so a world model trained on them alone
has never seen an attempt fail and imagines success under any policy; GRPO inside such a simulator
learns to please it (measured on `small`: imagined success 0.68 -> 0.92 while real success fell
0.21 -> 0.07). The paper and WoVR train on policy rollouts. This module records them: the supervised
policy acts in MuJoCo's C engine from the training initial states, with *sampled* actions (GRPO's
own behaviour distribution), re-planning every ``rl.env.execute_steps`` actions, for a fixed number of
steps whatever happens (the episode keeps going after a success or a drop), and every step is
rendered like the expert data (agentview RGB, depth and segmentation, JAX renderer) and written in
the same LIBERO layout, so the pipeline's latents stage reads both files alike.

Episodes are made in lockstep batches: one batched render per step and one batched policy call per
decision for the whole batch.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import sim
from sim import controller as ctl
from sim import tasks
from sim.datagen import (GenDataConfig, JaxFrames, dataset_info, flat_state, init_states, make_episode, model_xml,
                         render_scene)
from sim.dataset import DatasetWriter
from sword_jax.rl.policy import tokenize_instructions


def record_policy_episodes(act: Any, params: Any, rl_cfg: Any, gen: GenDataConfig, *,
                           key: jax.Array, batch: int = 32) -> Iterator[tuple[Any, bool]]:
    """``(Episode, success)`` for each of ``gen.episodes`` training initial states of each task in ``gen.tasks``.

    Args:
      act: :func:`sword_jax.rl.env_rollout.make_act_fns` of the policy.
      params: the policy's parameters.
      rl_cfg: chunking (``execute_steps``), proprio size and instruction length of the policy.
      gen: which initial states (``init_split``, ``init_start``, ``episodes``, ``init_seed``), the step
        count (``max_steps``: every episode has exactly this many actions) and the frame size.
      key: sampling randomness; decision ``c`` of batch ``b`` uses ``fold_in(fold_in(key, b), c)``.
      batch: episodes stepped together (the batch's size is the policy's; another size samples other actions).

    The recorded action is the one executed (there is no separate label), success is the simulator's.
    Each step's frames are rendered once, for the whole batch: the policy reads them at its decisions and
    the file stores them all (the renderer's output does not depend on which frames share a call).
    """
    starts = [(task, index, qpos) for task in gen.tasks for index, qpos in enumerate(init_states(gen, task))]
    envs: dict[int, Any] = {}
    frames = None
    k = rl_cfg.env.execute_steps
    for b, begin in enumerate(range(0, len(starts), batch)):
        group = starts[begin:begin + batch]
        for task, _, _ in group:
            if task not in envs:
                envs[task] = sim.load("libero_spatial", task_id=task, backend="cpu", resolution=gen.resolution,
                                      max_steps=gen.max_steps)
        if frames is None:
            frames = JaxFrames(render_scene(envs[group[0][0]]), gen.resolution)
        group_envs = [envs[task] for task, _, _ in group]
        # stepped in place: the MjData copy of a pure step costs more than the physics, and no old state is kept
        states = [env.reset_to(qpos) for env, (_, _, qpos) in zip(group_envs, group)]
        record = _BatchRecord(len(group), gen.max_steps)
        text = jnp.asarray(tokenize_instructions([tasks.LANGUAGE[task] for task, _, _ in group],
                                                 rl_cfg.policy.max_instruction_bytes))
        for t in range(gen.max_steps):
            agent = record.observe(t, states, frames([s.data for s in states], "agentview"))
            if t % k == 0:
                proprio = np.stack([np.asarray(s.obs["proprio"], np.float32) for s in states])[:, : rl_cfg.proprio_dim]
                _, _, _, chunk = act(params, jnp.asarray(agent["rgb"]), text, jnp.asarray(proprio),
                                     jax.random.fold_in(jax.random.fold_in(key, b), t // k), False)
                chunk = np.clip(np.asarray(chunk, np.float64), -1.0, 1.0)  # (B, chunk_len, 7)
            record.actions[:, t] = chunk[:, t % k]
            states = [env.step_inplace(s, a) for env, s, a in zip(group_envs, states, record.actions[:, t])]
            record.after[:, t] = [float(s.done) for s in states]
        for i, (task, index, _) in enumerate(group):
            env = envs[task]
            episode = make_episode(
                gen, task, index, env, model_xml(env), actions=record.actions[i], executed=record.actions[i],
                after=record.after[i], flat=record.flat[i],
                agent={name: values[i] for name, values in record.agent.items()}, wrist=None,
                proprio=record.proprio[i], joints=record.joints[i])
            yield episode, bool(record.after[i].max() > 0)


class _BatchRecord:
    """A batch's ``n`` episodes of ``steps`` steps, filled one step at a time: arrays (n, steps, ...)."""

    def __init__(self, n: int, steps: int):
        self.n, self.steps = n, steps
        self.actions = np.zeros((n, steps, ctl.ACTION_DIM))
        self.after = np.zeros((n, steps))
        self.joints = np.zeros((n, steps, 7))
        self.flat = self.proprio = np.zeros((n, steps, 0))  # sized at step 0 by what the states hold
        self.agent: dict[str, np.ndarray] = {}

    def observe(self, t: int, states: list[Any], agent: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Stores step ``t``'s states (before its action) and their frames ``agent`` (rgb, depth, seg; leading
        axis ``n``); returns ``agent``."""
        flat = np.stack([flat_state(s.data) for s in states])  # (n, 1 + nq + nv)
        proprio = np.stack([np.asarray(s.obs["proprio"]) for s in states])  # (n, 8)
        if t == 0:
            self.flat, self.proprio = (np.zeros((self.n, self.steps) + v.shape[1:], v.dtype) for v in (flat, proprio))
            self.agent = {name: np.zeros((self.n, self.steps) + v.shape[1:], v.dtype) for name, v in agent.items()}
        self.flat[:, t], self.proprio[:, t] = flat, proprio
        self.joints[:, t] = [s.data.qpos[:7] for s in states]  # copied: the data is stepped in place
        for name, values in agent.items():
            self.agent[name][:, t] = values
        return agent


def write_policy_episodes(path: str, act: Any, params: Any, rl_cfg: Any, gen: GenDataConfig, *,
                          key: jax.Array) -> dict:
    """Records :func:`record_policy_episodes` into ``path`` (LIBERO layout); returns a summary.

    Raises:
      FileExistsError: ``path`` exists and ``gen.overwrite`` is False (nothing is touched).
    """
    info = dataset_info(dataclasses.replace(gen, renderer="jax"), None)
    info.env_args["env_kwargs"]["source"] = "supervised policy, sampled actions"
    info.seg_class_names = render_scene(_any_env(gen)).class_names
    written = successes = 0
    with DatasetWriter(path, info, overwrite=gen.overwrite) as writer:
        for episode, success in record_policy_episodes(act, params, rl_cfg, gen, key=key):
            writer.add(episode)
            written += 1
            successes += int(success)
    return {"path": path, "episodes": written, "success_rate": successes / max(written, 1)}


def _any_env(gen: GenDataConfig) -> Any:
    return sim.load("libero_spatial", task_id=gen.tasks[0], backend="cpu", resolution=gen.resolution,
                    max_steps=gen.max_steps)
