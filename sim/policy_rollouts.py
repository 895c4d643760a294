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
decision for the whole batch. The batches can be split over worker processes (``workers``): each
records every ``workers``-th batch with the same keys into files of its own, so the physics (one
process steps its batch's envs one after the other) and the frames' compression run side by side,
and the file they make holds the same episodes, bit for bit and in the same order, as one process's.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import shutil
import tempfile
import traceback
from collections.abc import Callable, Iterator, Sequence
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


def record_policy_episodes(act: Any, params: Any, rl_cfg: Any, gen: GenDataConfig, *, key: jax.Array,
                           batch: int = 32, batches: Sequence[int] | None = None) -> Iterator[tuple[Any, bool]]:
    """``(Episode, success)`` for each of ``gen.episodes`` training initial states of each task in ``gen.tasks``.

    Args:
      act: :func:`sword_jax.rl.env_rollout.make_act_fns` of the policy.
      params: the policy's parameters.
      rl_cfg: chunking (``execute_steps``), proprio size and instruction length of the policy.
      gen: which initial states (``init_split``, ``init_start``, ``episodes``, ``init_seed``), the step
        count (``max_steps``: every episode has exactly this many actions) and the frame size.
      key: sampling randomness; decision ``c`` of batch ``b`` uses ``fold_in(fold_in(key, b), c)``.
      batch: episodes stepped together (the batch's size is the policy's; another size samples other actions).
      batches: which batches to record, in the order given (default all): batch ``b`` holds episodes
        ``b * batch`` to ``(b + 1) * batch`` of the tasks' initial states in order, and is the same whichever
        others are recorded with it.

    The recorded action is the one executed (there is no separate label), success is the simulator's.
    Each step's frames are rendered once, for the whole batch: the policy reads them at its decisions and
    the file stores them all (the renderer's output does not depend on which frames share a call).
    """
    starts = [(task, index, qpos) for task in gen.tasks for index, qpos in enumerate(init_states(gen, task))]
    envs: dict[int, Any] = {}
    frames = None
    k = rl_cfg.env.execute_steps
    for b in range(-(-len(starts) // batch)) if batches is None else batches:
        group = starts[b * batch:(b + 1) * batch]
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


def write_policy_episodes(path: str, make_act: Callable[[], Any], params: Any, rl_cfg: Any, gen: GenDataConfig, *,
                          key: jax.Array, batch: int = 32, workers: int = 1) -> dict:
    """Records :func:`record_policy_episodes` into ``path`` (LIBERO layout); returns a summary.

    Args:
      make_act: returns the policy's act fns (:func:`sword_jax.rl.env_rollout.make_act_fns`); called in each
        process that records, so with ``workers > 1`` it is pickled to them
        (``functools.partial(make_act_fns, graphdef, rl_cfg)``).
      params, rl_cfg, gen, key, batch: as for :func:`record_policy_episodes`.
      workers: processes that record the batches (1 = this process): worker ``w`` records batches
        ``w, w + workers, ...`` into files of its own, which are then copied into ``path`` in batch order.
        The file and the summary are those of one process, bit for bit.

    Raises:
      FileExistsError: ``path`` exists and ``gen.overwrite`` is False (nothing is touched).
      ValueError: ``workers < 1``.
      RuntimeError: a worker failed (the message names it and holds its traceback); nothing is written.
    """
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if os.path.exists(path) and not gen.overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    info = dataset_info(dataclasses.replace(gen, renderer="jax"), None)
    info.env_args["env_kwargs"]["source"] = "supervised policy, sampled actions"
    info.seg_class_names = render_scene(_any_env(gen)).class_names
    if workers == 1:
        written = successes = 0
        with DatasetWriter(path, info, overwrite=gen.overwrite) as writer:
            for episode, success in record_policy_episodes(make_act(), params, rl_cfg, gen, key=key, batch=batch):
                writer.add(episode)
                written += 1
                successes += int(success)
    else:
        written, successes = _write_in_workers(path, make_act, params, rl_cfg, gen, info, key=key, batch=batch,
                                               workers=workers)
    return {"path": path, "episodes": written, "success_rate": successes / max(written, 1)}


def _batch_file(folder: str, b: int) -> str:
    return os.path.join(folder, f"batch{b:06d}.hdf5")


def _write_in_workers(path: str, make_act: Callable[[], Any], params: Any, rl_cfg: Any, gen: GenDataConfig,
                      info: Any, *, key: jax.Array, batch: int, workers: int) -> tuple[int, int]:
    """``workers`` spawned processes record the batches into one file per batch in a temporary folder beside
    ``path``, copied into ``path`` in batch order; returns ``(episodes, successes)``. The folder is removed
    whatever happens; a failing worker stops the others."""
    import multiprocessing
    from multiprocessing.connection import wait

    episodes = len(gen.tasks) * gen.episodes
    num_batches = -(-episodes // batch)
    workers = min(workers, num_batches)
    folder = tempfile.mkdtemp(prefix=".policy_data_", dir=os.path.dirname(os.path.abspath(path)))
    # spawn: a forked child would inherit this process's JAX runtime (threads, device handles). Only host
    # arrays are sent: unpickling a device array would start a child's JAX backend before it sets its memory
    # policy (see _record_worker). The parameters go through a file: a child that dies while starting would
    # leave this process blocked for good on a start pipe still holding more than its buffer.
    context = multiprocessing.get_context("spawn")
    key_data, key_impl = np.asarray(jax.random.key_data(key)), str(jax.random.key_impl(key))
    procs, pending = [], {}
    try:
        params_file = os.path.join(folder, "params.pickle")
        with open(params_file, "wb") as f:
            pickle.dump(jax.device_get(params), f, protocol=pickle.HIGHEST_PROTOCOL)
        for w in range(workers):
            receive, send = context.Pipe(duplex=False)
            proc = context.Process(target=_record_worker, name=f"policy_data worker {w}", daemon=True,
                                   args=(send, make_act, params_file, rl_cfg, gen, key_data, key_impl, batch,
                                         list(range(w, num_batches, workers)), folder))
            proc.start()
            send.close()  # the child holds the only writing end: its exit ends the pipe
            procs.append(proc)
            pending[receive] = w
        written = successes = 0
        while pending:
            for conn in wait(list(pending)):
                w = pending.pop(conn)
                try:
                    status, payload = conn.recv()
                except EOFError:
                    procs[w].join()
                    raise RuntimeError(f"policy_data worker {w} of {workers} exited with code {procs[w].exitcode} "
                                       "before it finished its batches") from None
                if status != "done":
                    raise RuntimeError(f"policy_data worker {w} of {workers} (batches {w}, {w + workers}, ...) "
                                       f"failed:\n{payload}")
                written, successes = written + payload[0], successes + payload[1]
        with DatasetWriter(path, info, overwrite=gen.overwrite) as writer:
            for b in range(num_batches):  # stored chunks copied as they are (no decompress / compress again)
                writer.add_file(_batch_file(folder, b))
        return written, successes
    finally:
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
            proc.join()
        shutil.rmtree(folder, ignore_errors=True)


def _record_worker(conn: Any, make_act: Callable[[], Any], params_file: str, rl_cfg: Any, gen: GenDataConfig,
                   key_data: np.ndarray, key_impl: str, batch: int, batches: list[int], folder: str) -> None:
    """One worker process of :func:`write_policy_episodes`: records ``batches`` with the policy's parameters
    pickled in ``params_file``, each batch into its own file in ``folder``; sends ``("done", (episodes,
    successes))`` or ``("failed", traceback)``."""
    # the workers share the accelerator with each other and the parent: each allocates what it uses, no more
    # (read when JAX starts its backend, at the first array below)
    os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    try:
        with open(params_file, "rb") as f:
            params = jax.device_put(pickle.load(f))  # once, not at every policy call
        key = jax.random.wrap_key_data(jnp.asarray(key_data), impl=key_impl)
        info = dataset_info(dataclasses.replace(gen, renderer="jax"), None)
        recorded = record_policy_episodes(make_act(), params, rl_cfg, gen, key=key, batch=batch, batches=batches)
        total = len(gen.tasks) * gen.episodes
        written = successes = 0
        for b in batches:
            with DatasetWriter(_batch_file(folder, b), info) as writer:
                for _ in range(min(batch, total - b * batch)):
                    episode, success = next(recorded)
                    writer.add(episode)
                    written += 1
                    successes += int(success)
        conn.send(("done", (written, successes)))
    except BaseException:  # noqa: BLE001 - reported to the parent, which fails the stage naming this worker
        conn.send(("failed", traceback.format_exc()))
    finally:
        conn.close()


def _any_env(gen: GenDataConfig) -> Any:
    return sim.load("libero_spatial", task_id=gen.tasks[0], backend="cpu", resolution=gen.resolution,
                    max_steps=gen.max_steps)
