"""Expert demonstrations in LIBERO's HDF5 layout (+ depth and segmentation): :func:`generate`
writes what a :class:`GenDataConfig` describes (``python -m train.gen_data`` is its command line).

Two kinds of episode:

* fixed length (default; world-model data): every episode is exactly ``max_steps`` steps and
  the expert keeps moving after it succeeds (``sim.expert`` with ``cycle``: it grasps the bowl
  again, moves it to a free table spot, back to the plate, ...), so there is motion over the
  whole horizon and no padding. ``rewards[t]`` stays LIBERO's "task solved after action t"
  (it drops back to 0 while the bowl is away); ``first_success`` records the first such t.
* ``stop_at_success`` (behaviour-cloning demos): as LIBERO, an episode ends at its first
  success (or after ``max_steps``).

``episodes`` is per task. Episode ``i`` of task ``k`` starts from initial state
``init_start + i`` of the task's ``init_split`` (``sim.tasks.split_init_states``): ``train``
(default; demonstrations and world-model training) and ``heldout`` (world-model evaluation)
are seeded streams checked disjoint from ``eval``, the 50 fixed states policies are evaluated
on (as in LIBERO, demonstrations never start from an evaluation state). Each demo records its
``init_split`` / ``init_state_id``. The expert's action noise is seeded by ``(seed, k, i)``
and applied DART style: the noisy action is executed (``executed_actions``), the clean one is
the label (``actions``); ``noisy_share`` of the episodes (spread evenly) are noisy, the rest
clean. Noisy rollouts can fail; failures are kept. The CPU backend runs MuJoCo's C engine one episode at a time; the MJX
backend rolls all episodes of a task out at once in one jitted ``lax.scan`` (vmapped),
rendering inside it.

Rendering (``renderer``): ``jax`` is the ray-cast renderer of ``sim/render.py`` (the only
one on the MJX backend); ``gl`` is MuJoCo's OpenGL renderer through ``sim/render_gl.py``
(CPU backend only; same geoms, classes, depth convention, materials and lights, plus
MuJoCo's specular highlights). ``auto`` (default) picks ``gl`` on the CPU backend where an
OpenGL context can be made, because it is ~100x faster there at 128 px (see
``benchmarks/render_speed.py``), and ``jax`` otherwise.

Observation ``t`` is what was seen before ``actions[t]``; ``rewards[t]``/``dones[t]`` are
the success after it, and the last step of every episode has ``dones = 1`` (as LIBERO).
"""


from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any

import numpy as np
from tqdm import tqdm

import sim
from sim import expert, render, tasks
from sim.dataset import DatasetInfo, DatasetWriter, Episode, read_info
from sim.scene import build_model, scene_xml

_CHUNK = 16  # frames per JAX render call (fixed, so there is one compile per camera)


def render_scene(env: Any) -> Any:
    """The JAX renderer's ``RenderScene`` of ``env``'s scene, one per physics timestep (jit caches key on it)."""
    return _render_scene(float(env.config.physics_dt))


@functools.lru_cache(maxsize=8)
def _render_scene(physics_dt: float) -> Any:
    return render.build_scene(build_model(timestep=physics_dt))


@dataclasses.dataclass(frozen=True)
class GenDataConfig:
    """What ``generate`` writes (see the module docstring)."""

    out: str
    tasks: tuple[int, ...] = (0,)
    episodes: int = 1
    backend: str = "cpu"
    resolution: int = 128
    noise: float = 0.0
    seed: int = 0
    renderer: str = "auto"
    max_steps: int = 220
    wrist_camera: bool = True
    overwrite: bool = False
    stop_at_success: bool = False
    noisy_share: float = 1.0
    noise_correlation: float = 0.0  # the expert noise's step-to-step correlation (ExpertConfig.noise_correlation)
    init_split: str = "train"
    init_start: int = 0
    init_seed: int = 0

    def validate(self) -> None:
        if not self.tasks or any(not 0 <= t <= 9 for t in self.tasks):
            raise ValueError(f"tasks must be ids in 0..9, got {self.tasks}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if self.backend not in ("cpu", "mjx"):
            raise ValueError(f"backend must be cpu|mjx, got {self.backend!r}")
        if self.resolution < 16 or self.resolution % 16:
            raise ValueError(f"resolution must be a positive multiple of 16, got {self.resolution}")
        if not 0 <= self.noise <= 1:
            raise ValueError(f"noise must be in [0, 1], got {self.noise}")
        if not 0 <= self.noisy_share <= 1:
            raise ValueError(f"noisy_share must be in [0, 1], got {self.noisy_share}")
        if not 0 <= self.noise_correlation < 1:  # also rejects NaN
            raise ValueError(f"noise_correlation must be in [0, 1), got {self.noise_correlation}")
        if self.renderer not in ("auto", "jax", "gl"):
            raise ValueError(f"renderer must be auto|jax|gl, got {self.renderer!r}")
        if self.renderer == "gl" and self.backend != "cpu":
            raise ValueError("renderer=gl needs backend=cpu (MuJoCo's OpenGL renderer reads MjData)")
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")
        if self.init_split not in tasks.INIT_SPLITS:
            raise ValueError(f"init_split must be one of {tasks.INIT_SPLITS}, got {self.init_split!r}")
        limit = tasks.NUM_INIT_STATES if self.init_split == "eval" else tasks.TRAIN_RESERVE
        if self.init_start < 0 or self.init_start + self.episodes > limit:
            raise ValueError(f"init states {self.init_start}..{self.init_start + self.episodes - 1} are outside the "
                             f"{self.init_split} split's {limit} per task")
        if not self.out.endswith((".hdf5", ".h5")):
            raise ValueError(f"out must be an .hdf5/.h5 file, got {self.out!r}")
        if os.path.exists(self.out) and not self.overwrite:
            raise FileExistsError(f"{self.out} exists; pass --overwrite to replace it")


def config_from_sim(sim_config: Any, out: str, *, seed: int = 0, overwrite: bool = False,
                    init_split: str = "train", episode_steps: int | None = None) -> GenDataConfig:
    """The ``GenDataConfig`` of an experiment's ``sim`` section (``SimConfig``).

    With ``episode_steps`` (or ``sim_config.episode_steps`` > 0) episodes are fixed length;
    otherwise they stop at success, at most ``sim_config.max_steps`` long.
    """
    steps = episode_steps or sim_config.episode_steps
    return GenDataConfig(out=out, tasks=tuple(sim_config.tasks), episodes=sim_config.episodes_per_task,
                         backend=sim_config.backend, resolution=sim_config.resolution,
                         noise=sim_config.expert_noise, noisy_share=sim_config.noisy_share, seed=seed,
                         max_steps=steps or sim_config.max_steps, stop_at_success=not steps,
                         wrist_camera=True, overwrite=overwrite, init_split=init_split,
                         init_seed=sim_config.init_seed)


def noisy(cfg: GenDataConfig, index: int) -> bool:
    """Whether episode ``index`` (of each task) is a noisy one: ``noisy_share`` of them, spread evenly."""
    return cfg.noise > 0 and int((index + 1) * cfg.noisy_share) > int(index * cfg.noisy_share)


def expert_config(cfg: GenDataConfig) -> Any:
    return expert.ExpertConfig(noise=cfg.noise, noise_correlation=cfg.noise_correlation, cycle=not cfg.stop_at_success)


def init_states(cfg: GenDataConfig, task: int) -> np.ndarray:
    """(episodes, nq) initial states of ``task``'s episodes: ``init_start ..`` of ``cfg.init_split``."""
    return tasks.split_init_states(task, cfg.init_split, cfg.episodes, start=cfg.init_start, seed=cfg.init_seed)


def flat_state(data: Any) -> np.ndarray:
    """LIBERO/robosuite's flattened sim state: [time, qpos, qvel]."""
    return np.concatenate([[float(data.time)], np.asarray(data.qpos), np.asarray(data.qvel)])


class JaxFrames:
    """Chunked JAX rendering of a list of ``MjData`` (one compile per camera and size)."""

    def __init__(self, scene: Any, resolution: int):
        self.scene, self.resolution = scene, resolution

    def __call__(self, datas: list[Any], camera: str) -> dict[str, np.ndarray]:
        rendered = []  # every chunk is dispatched before any is read back, so the next one's poses are gathered
        for start in range(0, len(datas), _CHUNK):  # while the device renders this one
            chunk = datas[start:start + _CHUNK]
            padded = chunk + [chunk[-1]] * (_CHUNK - len(chunk))
            frame = render.render_mjdata(self.scene, padded, camera, height=self.resolution, width=self.resolution)
            rendered.append((frame, len(chunk)))
        return {name: np.concatenate([np.asarray(getattr(frame, name))[:n] for frame, n in rendered])
                for name in ("rgb", "depth", "seg")}


class _GLFrames:
    """MuJoCo's OpenGL renderer over a list of ``MjData``."""

    def __init__(self, model: Any, scene: Any, resolution: int, cameras: tuple[str, ...]):
        from sim.render_gl import GLRenderer

        self.renderers = {c: GLRenderer(model, scene, c, height=resolution, width=resolution) for c in cameras}

    def __call__(self, datas: list[Any], camera: str) -> dict[str, np.ndarray]:
        frames = [self.renderers[camera].render(d) for d in datas]
        return {name: np.stack([getattr(f, name) for f in frames]) for name in ("rgb", "depth", "seg")}


def _cpu_episodes(cfg: GenDataConfig, task: int, env: Any, frames: Any, bar: tqdm):
    xml = model_xml(env)
    for i, qpos in enumerate(init_states(cfg, task)):
        rng = np.random.default_rng([cfg.seed, task, i])
        clean = not noisy(cfg, i)
        out = expert.rollout_cpu(env, qpos, cfg=dataclasses.replace(expert_config(cfg), noise=0.0) if clean
                                 else expert_config(cfg), rng=rng, max_steps=cfg.max_steps, record=True,
                                 stop_at_success=cfg.stop_at_success)
        states = out["states"]
        if len(out["actions"]) == 0:  # solved at reset: nothing to learn from
            bar.update(1)
            continue
        seen = [s.data for s in states[:-1]]
        agent = frames(seen, "agentview")
        wrist = frames(seen, "eye_in_hand")["rgb"] if cfg.wrist_camera else None
        proprio = np.stack([np.asarray(s.obs["proprio"]) for s in states[:-1]])
        after = np.asarray([float(s.done) for s in states[1:]])
        flat = np.stack([flat_state(d) for d in seen])
        yield make_episode(cfg, task, i, env, xml, actions=out["actions"], executed=out["executed"], after=after,
                           flat=flat, agent=agent, wrist=wrist, proprio=proprio,
                           joints=np.stack([np.asarray(d.qpos[:7]) for d in seen])), bool(out["success"])
        bar.update(1)


def make_episode(cfg: GenDataConfig, task: int, index: int, env: Any, xml: str, *, actions: np.ndarray,
                 executed: np.ndarray, after: np.ndarray, flat: np.ndarray, agent: dict[str, np.ndarray],
                 wrist: np.ndarray | None, proprio: np.ndarray, joints: np.ndarray) -> Any:
    """One ``Episode`` from the recorded arrays (T steps; ``after[t]`` = success after action t)."""
    dones = after.astype(np.float64)
    dones[-1] = 1.0
    hits = np.flatnonzero(after > 0)
    return Episode(
        actions=np.asarray(actions, np.float64), states=flat.astype(np.float64), rewards=after.astype(np.float64),
        dones=dones, agentview_rgb=agent["rgb"], agentview_depth=agent["depth"], agentview_seg=agent["seg"],
        eye_in_hand_rgb=wrist, ee_states=proprio[:, :6], gripper_states=proprio[:, 6:8], joint_states=joints,
        init_state=flat[0].astype(np.float64), model_file=xml, task_id=task, language_instruction=env.language,
        executed_actions=np.asarray(executed, np.float64), init_split=cfg.init_split,
        init_state_id=cfg.init_start + index, first_success=int(hits[0]) if hits.size else -1,
    )


def _mjx_episodes(cfg: GenDataConfig, task: int, env: Any, scene: Any, bar: tqdm):
    import jax
    import jax.numpy as jnp

    xml = model_xml(env)
    res = cfg.resolution
    agent_view = render.make_renderer(scene, "agentview", height=res, width=res)
    wrist_view = render.make_renderer(scene, "eye_in_hand", height=res, width=res)

    def observe(state):
        frame, data = agent_view(state.data), state.data
        return {
            "rgb": frame.rgb, "depth": frame.depth, "seg": frame.seg.astype(jnp.uint8),
            "wrist": wrist_view(data).rgb if cfg.wrist_camera else jnp.zeros((1,), jnp.uint8),
            "proprio": state.obs["proprio"], "joints": data.qpos[:7],
            "flat": jnp.concatenate([jnp.reshape(data.time, (1,)), data.qpos, data.qvel]).astype(jnp.float32),
        }

    def rollout(qpos, key, noise_gain):
        _, records = expert.episode_mjx(env, qpos, jax.random.split(key, cfg.max_steps), expert_config(cfg),
                                        noise_gain=noise_gain, observe=observe)
        return records

    root = jax.random.fold_in(jax.random.key(cfg.seed), task)
    qpos = jnp.asarray(init_states(cfg, task), jnp.float32)
    keys = jax.random.split(root, cfg.episodes)
    gains = jnp.asarray([float(noisy(cfg, i)) for i in range(cfg.episodes)], jnp.float32)
    with jax.numpy_dtype_promotion("standard"):  # MJX relies on implicit promotion
        records = jax.device_get(jax.jit(jax.vmap(rollout))(qpos, keys, gains))
    for i in range(cfg.episodes):
        done = np.asarray(records["done"][i]) > 0
        length = int(np.argmax(done)) + 1 if done.any() and cfg.stop_at_success else cfg.max_steps
        take = {k: np.asarray(v[i][:length]) for k, v in records.items()}
        yield make_episode(cfg, task, i, env, xml, actions=take["actions"], executed=take["executed"],
                           after=take["done"].astype(np.float64), flat=take["flat"],
                           agent={k: take[k] for k in ("rgb", "depth", "seg")},
                           wrist=take["wrist"] if cfg.wrist_camera else None, proprio=take["proprio"],
                           joints=take["joints"]), bool(done.any())
        bar.update(1)


def model_xml(env: Any) -> str:
    """The scene's MJCF as stored in each episode's ``model_file`` (``env``'s physics timestep)."""
    return scene_xml(timestep=env.config.physics_dt)


def _generate_task_file(cfg: GenDataConfig) -> str:
    """One task's file, in a worker process of :func:`generate` (``workers > 1``)."""
    return generate(cfg, progress=False)


def _generate_parallel(cfg: GenDataConfig, workers: int, progress: bool) -> str:
    """:func:`generate` with one process per task (up to ``workers`` at once), then one file.

    Every episode depends only on ``(seed, task, index)`` (its noise stream, its initial state), so
    the merged file holds the same episodes, in the same order, as the one-process run.
    """
    import concurrent.futures
    import multiprocessing
    import shutil
    import tempfile

    if os.path.exists(cfg.out) and not cfg.overwrite:
        raise FileExistsError(f"{cfg.out} exists (pass overwrite=True / --overwrite to replace it)")
    tmp = tempfile.mkdtemp(prefix=".gen_data_", dir=os.path.dirname(os.path.abspath(cfg.out)))
    try:
        parts = [dataclasses.replace(cfg, tasks=(task,), out=os.path.join(tmp, f"task{task}.hdf5"), overwrite=True)
                 for task in cfg.tasks]
        # spawn: a forked child would inherit this process's JAX runtime (threads, device handles)
        context = multiprocessing.get_context("spawn")
        with concurrent.futures.ProcessPoolExecutor(min(workers, len(parts)), mp_context=context) as pool:
            files = list(pool.map(_generate_task_file, parts))
        info = dataset_info(cfg, read_info(files[0]).seg_class_names)
        written = 0
        with DatasetWriter(cfg.out, info, overwrite=cfg.overwrite) as writer:
            for path in files:  # stored chunks copied as they are (no decompress / compress again)
                written += writer.add_file(path)
        if progress:
            print(f"gen_data: {written} episodes of {len(cfg.tasks)} tasks in {len(files)} processes -> {cfg.out}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return cfg.out


def dataset_info(cfg: GenDataConfig, seg_class_names):
    """The file's LIBERO-layout attributes for ``cfg`` (the renderer resolved)."""
    renderer = cfg.renderer
    if renderer == "auto":
        from sim.render_gl import gl_available

        renderer = "gl" if cfg.backend == "cpu" and gl_available()[0] else "jax"
    language = [tasks.LANGUAGE[t] for t in cfg.tasks]
    single = len(cfg.tasks) == 1
    problem = "libero_spatial" if not single else f"libero_spatial_{cfg.tasks[0]}"
    env_kwargs = {"tasks": list(cfg.tasks), "backend": cfg.backend, "camera_heights": cfg.resolution,
                  "camera_widths": cfg.resolution, "camera_names": ["agentview", "eye_in_hand"],
                  "control_freq": 20, "max_steps": cfg.max_steps, "expert_noise": cfg.noise, "seed": cfg.seed,
                  "renderer": renderer, "stop_at_success": cfg.stop_at_success, "noisy_share": cfg.noisy_share,
                  "init_split": cfg.init_split, "init_start": cfg.init_start,
                  "init_seed": cfg.init_seed,
                  **({"expert_noise_correlation": cfg.noise_correlation} if cfg.noise_correlation else {})}
    info = DatasetInfo(
        env_name=sim.GYM_ID,
        env_args={"type": 1, "env_name": sim.GYM_ID, "problem_name": problem, "bddl_file": "",
                  "env_kwargs": env_kwargs},
        problem_info={"problem_name": problem, "domain_name": "sword_libero_spatial",
                      "language_instruction": language[0] if single else " | ".join(language)},
        bddl_file_name=(language[0].replace(" ", "_") + ".bddl") if single else "",
        bddl_file_content="",  # the scene is built by sim/scene.py, not from a BDDL file
    )
    if seg_class_names is not None:
        info.seg_class_names = seg_class_names
    return info


def generate(cfg: GenDataConfig, *, progress: bool = True, workers: int = 0) -> str:
    """Runs the expert on every task/episode of ``cfg`` and writes ``cfg.out``; returns the path.

    ``workers > 1`` generates the tasks in that many processes at once (the C engine and the
    expert are single-threaded); the file is the same as with one process.

    Raises:
      ValueError / FileExistsError: invalid config or an existing output without overwrite.
    """
    cfg.validate()
    if workers > 1 and len(cfg.tasks) > 1:
        return _generate_parallel(cfg, workers, progress)
    info = dataset_info(cfg, None)
    renderer = info.env_args["env_kwargs"]["renderer"]
    successes = 0
    written = 0
    bar = tqdm(total=len(cfg.tasks) * cfg.episodes, desc="gen_data", unit="ep", disable=not progress)
    with DatasetWriter(cfg.out, info, overwrite=cfg.overwrite) as writer:
        for task in cfg.tasks:
            env = sim.load("libero_spatial", task_id=task, backend=cfg.backend, resolution=cfg.resolution,
                           max_steps=cfg.max_steps)
            scene = render_scene(env)
            info.seg_class_names = scene.class_names
            if cfg.backend == "cpu":
                frames = (_GLFrames(env.mj_model, scene, cfg.resolution, ("agentview", "eye_in_hand"))
                          if renderer == "gl" else JaxFrames(scene, cfg.resolution))
                episodes = _cpu_episodes(cfg, task, env, frames, bar)
            else:
                episodes = _mjx_episodes(cfg, task, env, scene, bar)
            for episode, success in episodes:
                writer.add(episode)
                written += 1
                successes += int(success)
                bar.set_postfix(task=task, success=f"{successes}/{written}")
    bar.close()
    if written == 0:
        raise RuntimeError("no episode was written (every episode was solved at reset)")
    return cfg.out
