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

Episodes are made in lockstep batches: one batched policy call per decision for the whole batch.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import sim
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
      batch: episodes stepped together.

    The recorded action is the one executed (there is no separate label), success is the simulator's.
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
        states = [[envs[task].reset_to(qpos)] for task, _, qpos in group]
        actions: list[list[np.ndarray]] = [[] for _ in group]
        text = jnp.asarray(tokenize_instructions([tasks.LANGUAGE[task] for task, _, _ in group],
                                                 rl_cfg.policy.max_instruction_bytes))
        for c in range(math.ceil(gen.max_steps / k)):
            now = [s[-1] for s in states]
            rgb = frames([s.data for s in now], "agentview")["rgb"]
            proprio = np.stack([np.asarray(s.obs["proprio"], np.float32) for s in now])[:, : rl_cfg.proprio_dim]
            _, _, _, chunk = act(params, jnp.asarray(rgb), text, jnp.asarray(proprio),
                                 jax.random.fold_in(jax.random.fold_in(key, b), c), False)
            chunk = np.clip(np.asarray(chunk, np.float64), -1.0, 1.0)
            for i, (task, _, _) in enumerate(group):
                for j in range(k):
                    if len(actions[i]) >= gen.max_steps:
                        break
                    states[i].append(envs[task].step(states[i][-1], chunk[i, j]))
                    actions[i].append(chunk[i, j])
        for i, (task, index, _) in enumerate(group):
            env, seen = envs[task], [s.data for s in states[i][:-1]]
            after = np.asarray([float(s.done) for s in states[i][1:]])
            episode = make_episode(
                gen, task, index, env, model_xml(env), actions=np.stack(actions[i]),
                executed=np.stack(actions[i]), after=after, flat=np.stack([flat_state(d) for d in seen]),
                agent=frames(seen, "agentview"), wrist=None,
                proprio=np.stack([np.asarray(s.obs["proprio"]) for s in states[i][:-1]]),
                joints=np.stack([np.asarray(d.qpos[:7]) for d in seen]))
            yield episode, bool(after.max() > 0)


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
