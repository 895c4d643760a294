"""Many C-engine episodes advanced in lockstep, for batched policy evaluation and GRPO rollouts.

``LockstepEnvs`` owns N episodes (task id + initial ``qpos``, or a recorded flat state ``[time, qpos,
qvel]`` to continue from, each) on MuJoCo's C engine, split
over ``workers`` processes (0 = in this process). Each call advances every active episode by
up to ``k`` actions (stopping at success or the step limit) and returns what a policy needs:
the agentview frame and the 8-D proprio. Frames are rendered in ONE batched call of
``sim/render.py``'s JAX ray caster (the renderer of the MJX data path, so a policy trained on
that data sees no renderer shift), or per episode by MuJoCo's OpenGL renderer (``renderer="gl"``,
faster on a CPU, the look of ``train.gen_data --renderer gl``).

Why not MJX here: its JAX physics is unusably slow on a CPU (~10 env-steps/s), while the C
engine steps ~1,300 env-steps/s per core including the Python controller; a process per core
scales that linearly, and only frames the policy reads are rendered.
"""

from __future__ import annotations

import functools
import multiprocessing as mp
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

_RENDER_BUCKET = 64  # batch sizes are padded to a multiple of this (one compile per bucket)


def grasp_geoms(env: Any) -> tuple[np.ndarray, np.ndarray]:
    """The Panda's two finger-pad geoms and the target bowl's geoms in ``env``'s model."""
    model = env.mj_model
    pads = np.array([model.geom(f"panda_{side}_finger_pad").id for side in ("left", "right")])
    return pads, np.flatnonzero(model.geom_bodyid == env.bowl_body)


def _pads_touch(data: Any, pads: np.ndarray, bowl: np.ndarray) -> bool:
    """Whether both finger pads ``pads`` are in contact with a geom of the bowl ``bowl`` (a grasp)."""
    g1, g2 = np.asarray(data.contact.geom1[: data.ncon]), np.asarray(data.contact.geom2[: data.ncon])
    touching = np.concatenate([g1[np.isin(g2, bowl)], g2[np.isin(g1, bowl)]])
    return bool(np.all(np.isin(pads, touching)))


def pose(env: Any, data: Any, grasp: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, float, np.ndarray, bool]:
    """In ``env``'s ``data``: the target bowl's origin, its up axis' z, the plate's origin and whether both finger
    pads touch the bowl (``grasp``: :func:`grasp_geoms` of ``env``)."""
    return (np.array(data.xpos[env.bowl_body]), float(data.xmat[env.bowl_body].reshape(3, 3)[2, 2]),
            np.array(data.xpos[env.plate_body]), _pads_touch(data, *grasp))


class _Shard:
    """A slice of the episodes, stepped in one process."""

    def __init__(self, episodes: Sequence[tuple[int, np.ndarray]], resolution: int, max_steps: int, renderer: str,
                 success_fn: Callable[[Any, Any], bool] | None = None):
        from sim.config import SimConfig
        from sim.env import CpuEnv

        self.renderer = renderer
        self.success_fn = success_fn
        self.resolution = resolution
        self.max_steps = max_steps
        self._make_env = lambda t: CpuEnv(SimConfig(backend="cpu", resolution=resolution, max_steps=max_steps), t)
        self.envs: dict[int, Any] = {}
        self._gl: dict[int, Any] = {}
        self._grasp: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # per task: finger-pad and bowl geoms (poses)
        self._assign(episodes)
        any_env = next(iter(self.envs.values()))
        self.cam_id = any_env.mj_model.camera("agentview").id

    def _assign(self, episodes: Sequence[tuple[int, np.ndarray]]) -> None:
        self.task_of = [int(t) for t, _ in episodes]
        for t in sorted(set(self.task_of) - set(self.envs)):
            self.envs[t] = self._make_env(t)
        self.qpos = [np.asarray(q, np.float64) for _, q in episodes]
        self.steps = np.zeros(len(episodes), np.int64)

    def reset(self, episodes: Sequence[tuple[int, np.ndarray]] | None = None) -> dict[str, np.ndarray]:
        if episodes is not None:
            self._assign(episodes)
        # an initial qpos is settled into a new episode; a recorded flat state [time, qpos, qvel] is continued
        self.states = [self.envs[t].reset_to(q) if len(q) == self.envs[t].nq else self.envs[t].restore(q)
                       for t, q in zip(self.task_of, self.qpos)]
        self.steps[:] = 0
        return self.observe(np.ones(len(self.states), bool))

    def step(self, actions: np.ndarray, active: np.ndarray) -> dict[str, np.ndarray]:
        """Executes ``actions [n, k, 7]`` on active episodes until success or the step limit."""
        n, k = actions.shape[:2]
        success = np.zeros(n, bool)
        executed = np.zeros(n, np.int64)
        for i in np.flatnonzero(active):
            env, state = self.envs[self.task_of[i]], self.states[i]
            for j in range(k):
                if self.steps[i] >= self.max_steps:
                    break
                state = env.step_inplace(state, np.clip(actions[i, j], -1.0, 1.0))
                self.steps[i] += 1
                executed[i] += 1
                if (self.success_fn(env, state) if self.success_fn is not None else state.done):
                    success[i] = True
                    break
            self.states[i] = state
        out = self.observe(active)
        out.update(success=success, executed=executed, truncated=self.steps >= self.max_steps)
        return out

    def observe(self, which: np.ndarray) -> dict[str, np.ndarray]:
        proprio = np.stack([np.asarray(s.obs["proprio"], np.float32) for s in self.states])
        out: dict[str, np.ndarray] = {"proprio": proprio}
        if self.renderer == "gl":
            frames = np.zeros((len(self.states), self.resolution, self.resolution, 3), np.uint8)
            for i in np.flatnonzero(which):
                frames[i] = self._gl_frame(i)
            out["frames"] = frames
        else:
            datas = [s.data for s in self.states]
            out["geom_xpos"] = np.stack([d.geom_xpos for d in datas]).astype(np.float32)
            out["geom_xmat"] = np.stack([d.geom_xmat for d in datas]).astype(np.float32)
            out["cam_pos"] = np.stack([d.cam_xpos[self.cam_id] for d in datas]).astype(np.float32)
            out["cam_mat"] = np.stack([d.cam_xmat[self.cam_id] for d in datas]).astype(np.float32)
        return out

    def poses(self) -> dict[str, np.ndarray]:
        """Per episode, now: the target bowl's origin ``bowl [n, 3]``, its up axis' z ``bowl_up [n]``, the plate's
        origin ``plate [n, 3]``, whether both finger pads touch the target bowl ``held [n]`` and the flat state
        ``state [n, 1 + nq + nv]`` (``[time, qpos, qvel]``, what ``reset`` continues from)."""
        bowl, up, plate, held, state = [], [], [], [], []
        for t, s in zip(self.task_of, self.states):
            env, d = self.envs[t], s.data
            if t not in self._grasp:
                self._grasp[t] = grasp_geoms(env)
            for values, value in zip((bowl, up, plate, held), pose(env, d, self._grasp[t])):
                values.append(value)
            state.append(np.concatenate([[float(d.time)], d.qpos, d.qvel]))
        return {"bowl": np.stack(bowl), "bowl_up": np.asarray(up), "plate": np.stack(plate), "held": np.asarray(held),
                "state": np.stack(state)}

    def _gl_frame(self, i: int) -> np.ndarray:
        task = self.task_of[i]
        if task not in self._gl:
            from sim.gym_env import _Frames

            self._gl[task] = _Frames(self.envs[task].mj_model, self.resolution, "gl")
        return self._gl[task](self.states[i].data, "agentview")

    def close(self) -> None:
        for frames in self._gl.values():
            frames.close()
        self._gl = {}


def _worker(conn, episodes, resolution, max_steps, renderer, success_fn) -> None:
    import os

    os.environ["JAX_PLATFORMS"] = "cpu"  # a worker steps the C engine; it must not claim the accelerator
    shard = _Shard(episodes, resolution, max_steps, renderer, success_fn)
    try:
        while True:
            cmd, args = conn.recv()
            if cmd == "close":
                break
            conn.send(getattr(shard, cmd)(*args))
    except EOFError:
        pass
    finally:
        shard.close()
        conn.close()


class LockstepEnvs:
    """N LIBERO-Spatial episodes on the C engine, advanced together (see the module docstring).

    Args:
      episodes: ``(task_id, initial qpos)`` per episode, or ``(task_id, flat state)``: a dataset's
        ``states[t]`` (``[time, qpos, qvel]``), continued with no settling (``CpuEnv.restore``).
      resolution: rendered frame size.
      max_steps: step limit per episode (LIBERO-Spatial: 220).
      renderer: ``jax`` (batched ray caster, the MJX data's look) or ``gl`` (MuJoCo's OpenGL).
      workers: processes to step in (0 = this process).
      success_fn: ``(env, state) -> bool`` replacing the task's success (a module-level function
        when ``workers > 0``); default: LIBERO's ``On(bowl, plate)``.
    """

    def __init__(self, episodes: Sequence[tuple[int, np.ndarray]], *, resolution: int, max_steps: int = 220,
                 renderer: str = "jax", workers: int = 0, success_fn: Callable[[Any, Any], bool] | None = None):
        if not episodes:
            raise ValueError("LockstepEnvs needs at least one episode")
        if renderer not in ("jax", "gl"):
            raise ValueError(f"renderer must be jax|gl, got {renderer!r}")
        if max_steps < 1 or resolution < 8:
            raise ValueError(f"need max_steps >= 1 and resolution >= 8, got {max_steps}, {resolution}")
        from sim import tasks

        self.n = len(episodes)
        self.task_ids = np.asarray([int(t) for t, _ in episodes])
        self.language = [tasks.LANGUAGE[t] for t in self.task_ids]
        self.resolution, self.max_steps, self.renderer = resolution, max_steps, renderer
        workers = max(0, min(int(workers), self.n))
        bounds = np.linspace(0, self.n, max(workers, 1) + 1).astype(int)
        self._slices = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
        self._procs: list[Any] = []
        self._conns: list[Any] = []
        if workers == 0:
            self._local = _Shard(list(episodes), resolution, max_steps, renderer, success_fn)
        else:
            self._local = None
            ctx = mp.get_context("spawn")
            for sl in self._slices:
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=_worker, args=(child, list(episodes[sl]), resolution, max_steps, renderer,
                                                                 success_fn),
                                   daemon=True)
                proc.start()
                self._procs.append(proc)
                self._conns.append(parent)
        self._scene = None
        self.done = np.zeros(self.n, bool)
        self.success = np.zeros(self.n, bool)

    def _call(self, cmd: str, per_shard_args: list[tuple]) -> dict[str, np.ndarray]:
        if self._local is not None:
            return getattr(self._local, cmd)(*per_shard_args[0])
        for conn, args in zip(self._conns, per_shard_args):
            conn.send((cmd, args))
        parts = [conn.recv() for conn in self._conns]
        return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}

    def _frames(self, out: dict[str, np.ndarray]) -> np.ndarray:
        if "frames" in out:
            return out["frames"]
        from sim import render

        if self._scene is None:
            from sim import scene as sc

            self._scene = render.build_scene(sc.build_model())
        cam_id, fovy = self._scene.cameras["agentview"]
        n = out["geom_xpos"].shape[0]
        padded = -(-n // _RENDER_BUCKET) * _RENDER_BUCKET if n > _RENDER_BUCKET else n
        pad = lambda x: np.concatenate([x, np.repeat(x[-1:], padded - n, 0)]) if padded > n else x  # noqa: E731
        frame = render.render_batch(self._scene, pad(out["geom_xpos"]), pad(out["geom_xmat"]), pad(out["cam_pos"]),
                                    pad(out["cam_mat"]), fovy=fovy, height=self.resolution, width=self.resolution,
                                    static_camera="agentview" in self._scene.static_cameras)
        return np.asarray(frame.rgb[:n], np.uint8)

    def reset(self, episodes: Sequence[tuple[int, np.ndarray]] | None = None) -> dict[str, np.ndarray]:
        """Starts every episode from its initial state (or from new ``episodes``, as many as before:
        worker processes are reused); returns ``frames [N,H,W,3] uint8``, ``proprio [N,8]``."""
        if episodes is not None:
            if len(episodes) != self.n:
                raise ValueError(f"reset with {len(episodes)} episodes; these envs hold {self.n}")
            self.task_ids = np.asarray([int(t) for t, _ in episodes])
            from sim import tasks

            self.language = [tasks.LANGUAGE[t] for t in self.task_ids]
        self.done[:] = False
        self.success[:] = False
        args = [() if episodes is None else (list(episodes[sl]),) for sl in self._slices]
        out = self._call("reset", args)
        return {"frames": self._frames(out), "proprio": out["proprio"]}

    def step(self, actions: np.ndarray) -> dict[str, np.ndarray]:
        """Executes ``actions [N, k, 7]`` (k >= 1) on the episodes not yet done.

        Returns:
          ``frames``/``proprio`` after the actions, ``success [N]`` (reached during this call),
          ``executed [N]`` (actions actually taken) and ``done [N]`` (success or step limit, ever).
        """
        actions = np.asarray(actions, np.float32)
        if actions.ndim == 2:
            actions = actions[:, None]
        if actions.shape[0] != self.n or actions.shape[-1] != 7 or not np.all(np.isfinite(actions)):
            raise ValueError(f"actions must be finite [{self.n}, k, 7], got {actions.shape}")
        active = ~self.done
        out = self._call("step", [(actions[sl], active[sl]) for sl in self._slices])
        self.success |= out["success"]
        self.done |= out["success"] | out["truncated"]
        return {"frames": self._frames(out), "proprio": out["proprio"], "success": out["success"],
                "executed": out["executed"], "done": self.done.copy()}

    def poses(self) -> dict[str, np.ndarray]:
        """Every episode's target bowl, plate and flat state as they are now (:meth:`_Shard.poses`)."""
        return self._call("poses", [()] * len(self._slices))

    def close(self) -> None:
        for conn in self._conns:
            try:
                conn.send(("close", ()))
            except (BrokenPipeError, OSError):
                pass
        for proc in self._procs:
            proc.join(timeout=10)
            if proc.is_alive():
                proc.terminate()
        self._procs, self._conns = [], []
        if self._local is not None:
            self._local.close()

    def __enter__(self) -> "LockstepEnvs":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def lockstep_evaluation(tasks: Sequence[int], episodes_per_task: int, *, resolution: int, max_steps: int = 220,
                        renderer: str = "jax", workers: int = 0) -> dict[str, Any]:
    """``episodes``, ``envs_factory`` and ``max_steps`` of ``sword_jax.rl.policy_success.evaluate_in_sim``:
    each task's first ``episodes_per_task`` fixed evaluation initial states on :class:`LockstepEnvs`.

    Usage: ``evaluate_in_sim(graphdef, params, rl, **lockstep_evaluation([0, 1], 10, resolution=128))``.
    """
    from sim import tasks as sim_tasks

    episodes = sim_tasks.evaluation_episodes(tasks, episodes_per_task)
    factory = functools.partial(LockstepEnvs, resolution=resolution, max_steps=max_steps, renderer=renderer,
                                workers=workers)
    return {"episodes": episodes, "envs_factory": factory, "max_steps": max_steps}
