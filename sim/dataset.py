"""Episodes in LIBERO's HDF5 layout: a validated writer and a reader that also reads real LIBERO files.

Layout (as LIBERO's ``scripts/create_dataset.py`` writes it)::

    data/                       attrs: env_name, env_args (JSON), problem_info (JSON),
                                       bddl_file_name, bddl_file_content,
                                       macros_image_convention, num_demos, total
      demo_i/                   attrs: num_samples, model_file, init_state
        actions (T, 7)  states (T, S)  rewards (T,)  dones (T,)  [robot_states (T, R)]
        obs/agentview_rgb (T, H, W, 3) uint8   obs/eye_in_hand_rgb (T, H', W', 3) uint8
        obs/ee_states (T, 6)  obs/ee_pos (T, 3)  obs/ee_ori (T, 3)
        obs/gripper_states (T, 2)  obs/joint_states (T, 7)

plus, from this project, ``obs/agentview_depth`` (T, H, W) float32 metres and
``obs/agentview_seg`` (T, H, W) uint8 class ids (class names in the ``data`` attr
``seg_class_names``), ``executed_actions`` (T, 7) (what was executed when the expert's label
``actions`` was noised, DART style), and demo attrs ``task_id`` / ``language_instruction`` /
``init_split`` / ``init_state_id`` (which initial-state split and which state of it, see
``sim.tasks.split_init_states``) / ``first_success`` (index of the first step with
``rewards = 1``, -1 if none).

Images are written top row first (``macros_image_convention = "cv"``); LIBERO's own files are
``"opengl"`` (upside down) and the reader flips those, so every ``Episode`` it returns has row
0 at the top. Files are written to ``PATH.partial`` and renamed on close, so a crash never
leaves a truncated file under the final name, and an existing file is never overwritten
unless ``overwrite=True``.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterable, Sequence
from typing import Any

import h5py
import numpy as np

_REQUIRED_OBS = ("agentview_rgb", "ee_states", "gripper_states", "joint_states")
_OPTIONAL_OBS = ("eye_in_hand_rgb", "agentview_depth", "agentview_seg")
_PER_STEP = ("rewards", "dones", "states")
_INT_ATTRS = ("task_id", "init_state_id", "first_success")


class DatasetError(ValueError):
    """A file that is not a readable episode dataset in LIBERO's layout."""


@dataclasses.dataclass
class Episode:
    """One demonstration, numpy arrays with T steps (obs at t is seen before actions[t]).

    Attributes:
      actions: (T, 7) float. states: (T, S) flattened sim states ([time, qpos, qvel]).
      rewards, dones: (T,). agentview_rgb: (T, H, W, 3) uint8, row 0 at the top.
      ee_states: (T, 6) position + axis-angle. gripper_states: (T, 2). joint_states: (T, 7).
      eye_in_hand_rgb: (T, H', W', 3) uint8 or None.
      agentview_depth: (T, H, W) float32 metres or None. agentview_seg: (T, H, W) ints or None.
      init_state: (S,) the state the episode started from. model_file: the model's MJCF.
      task_id, language_instruction: task metadata (None / "" when unknown).
      executed_actions: (T, 7) the actions executed, where they differ from the labels
        ``actions`` (noisy expert, DART), or None (then ``actions`` were executed).
      init_split, init_state_id: the initial state's split and index in it ("" / None if unknown).
      first_success: index of the first step with ``rewards = 1`` (-1 none, None unknown).
    """

    actions: np.ndarray
    states: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    agentview_rgb: np.ndarray
    ee_states: np.ndarray
    gripper_states: np.ndarray
    joint_states: np.ndarray
    eye_in_hand_rgb: np.ndarray | None = None
    agentview_depth: np.ndarray | None = None
    agentview_seg: np.ndarray | None = None
    init_state: np.ndarray | None = None
    model_file: str = ""
    task_id: int | None = None
    language_instruction: str = ""
    executed_actions: np.ndarray | None = None
    init_split: str = ""
    init_state_id: int | None = None
    first_success: int | None = None

    @property
    def num_samples(self) -> int:
        return int(self.actions.shape[0])

    def validate(self, where: str = "episode") -> None:
        """Raises ``DatasetError`` naming the first inconsistent field."""
        actions = np.asarray(self.actions)
        if actions.ndim != 2 or actions.shape[0] == 0:
            raise DatasetError(f"{where}: actions must be (T>0, A), got {actions.shape}")
        if not np.all(np.isfinite(actions)):
            raise DatasetError(f"{where}: actions contain non-finite values")
        steps = actions.shape[0]
        for name in ("states", "rewards", "dones", "ee_states", "gripper_states", "joint_states", "executed_actions",
                     "agentview_rgb", "eye_in_hand_rgb", "agentview_depth", "agentview_seg"):
            value = getattr(self, name)
            if value is None:
                continue
            if np.shape(value)[:1] != (steps,):
                raise DatasetError(
                    f"{where}: length mismatch: {name} has {np.shape(value)[:1]} steps but actions has {steps}"
                )
        for name in ("agentview_rgb", "eye_in_hand_rgb"):
            image = getattr(self, name)
            if image is None:
                continue
            if image.ndim != 4 or image.shape[-1] != 3 or image.dtype != np.uint8:
                raise DatasetError(f"{where}: {name} must be (T, H, W, 3) uint8, got {image.shape} {image.dtype}")
        frame_hw = self.agentview_rgb.shape[1:3]
        for name in ("agentview_depth", "agentview_seg"):
            value = getattr(self, name)
            if value is not None and tuple(value.shape[1:]) != tuple(frame_hw):
                raise DatasetError(f"{where}: {name} must be (T, {frame_hw[0]}, {frame_hw[1]}), got {value.shape}")
        if self.agentview_depth is not None and not np.all(np.isfinite(self.agentview_depth)):
            raise DatasetError(f"{where}: agentview_depth contains non-finite values")
        if self.executed_actions is not None and np.shape(self.executed_actions) != actions.shape:
            raise DatasetError(f"{where}: executed_actions must be {actions.shape}, got {np.shape(self.executed_actions)}")
        if self.first_success is not None:
            hits = np.flatnonzero(np.asarray(self.rewards) > 0)
            expected = int(hits[0]) if hits.size else -1
            if self.first_success != expected:
                raise DatasetError(f"{where}: first_success is {self.first_success} but rewards first reach 1 at {expected}")


@dataclasses.dataclass
class DatasetInfo:
    """File-level attributes of ``data``."""

    env_name: str = ""
    env_args: dict[str, Any] = dataclasses.field(default_factory=dict)
    problem_info: dict[str, Any] = dataclasses.field(default_factory=dict)
    bddl_file_name: str = ""
    bddl_file_content: str = ""
    seg_class_names: tuple[str, ...] = ()
    num_demos: int = 0
    total: int = 0
    image_convention: str = "cv"


class DatasetWriter:
    """Streams episodes into ``path`` (via ``path.partial``, renamed on a clean close).

    Usage::

        with DatasetWriter(path, info) as writer:
            writer.add(episode)

    Raises:
      FileExistsError: ``path`` exists and ``overwrite`` is False.
    """

    def __init__(self, path: str | os.PathLike, info: DatasetInfo, *, overwrite: bool = False,
                 compression: str | None = "gzip"):
        self.path = os.fspath(path)
        if os.path.exists(self.path) and not overwrite:
            raise FileExistsError(f"{self.path} exists; pass overwrite=True to replace it")
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        self._partial = self.path + ".partial"
        self._file = h5py.File(self._partial, "w")
        self._info = info
        self._compression = compression
        self._data = self._file.create_group("data")
        self._count = 0
        self._total = 0

    def _dataset(self, group: h5py.Group, name: str, value: np.ndarray) -> None:
        big = value.ndim >= 3
        group.create_dataset(name, data=value, compression=self._compression if big else None)

    def add(self, episode: Episode) -> str:
        """Validates and appends one episode; returns its group name (``demo_i``)."""
        name = f"demo_{self._count}"
        episode.validate(name)
        if episode.agentview_seg is not None:
            seg = np.asarray(episode.agentview_seg)
            if seg.min(initial=0) < 0 or seg.max(initial=0) > 255:
                raise DatasetError(f"{name}: agentview_seg class ids must be in 0..255")
        grp = self._data.create_group(name)
        obs = grp.create_group("obs")
        ee = np.asarray(episode.ee_states, np.float64)
        self._dataset(obs, "agentview_rgb", np.asarray(episode.agentview_rgb, np.uint8))
        if episode.eye_in_hand_rgb is not None:
            self._dataset(obs, "eye_in_hand_rgb", np.asarray(episode.eye_in_hand_rgb, np.uint8))
        if episode.agentview_depth is not None:
            self._dataset(obs, "agentview_depth", np.asarray(episode.agentview_depth, np.float32))
        if episode.agentview_seg is not None:
            self._dataset(obs, "agentview_seg", np.asarray(episode.agentview_seg).astype(np.uint8))
        obs.create_dataset("ee_states", data=ee)
        obs.create_dataset("ee_pos", data=ee[:, :3])
        obs.create_dataset("ee_ori", data=ee[:, 3:])
        obs.create_dataset("gripper_states", data=np.asarray(episode.gripper_states, np.float64))
        obs.create_dataset("joint_states", data=np.asarray(episode.joint_states, np.float64))
        grp.create_dataset("actions", data=np.asarray(episode.actions, np.float64))
        if episode.executed_actions is not None:
            grp.create_dataset("executed_actions", data=np.asarray(episode.executed_actions, np.float64))
        grp.create_dataset("states", data=np.asarray(episode.states, np.float64))
        grp.create_dataset("robot_states", data=np.concatenate(
            [episode.gripper_states, ee[:, :3], ee[:, 3:]], axis=1).astype(np.float64))
        grp.create_dataset("rewards", data=np.asarray(episode.rewards, np.uint8))
        grp.create_dataset("dones", data=np.asarray(episode.dones, np.uint8))
        grp.attrs["num_samples"] = episode.num_samples
        grp.attrs["model_file"] = episode.model_file
        init = episode.init_state if episode.init_state is not None else episode.states[0]
        grp.attrs["init_state"] = np.asarray(init, np.float64)
        for attr in _INT_ATTRS:
            if getattr(episode, attr) is not None:
                grp.attrs[attr] = int(getattr(episode, attr))
        grp.attrs["language_instruction"] = episode.language_instruction
        if episode.init_split:
            grp.attrs["init_split"] = episode.init_split
        self._count += 1
        self._total += episode.num_samples
        return name

    def add_file(self, path: str | os.PathLike) -> int:
        """Appends every episode of another dataset file, in its order; returns how many.

        Episodes are copied as stored (HDF5 object copy: compressed chunks are not decompressed and
        compressed again), renumbered after the episodes already written; the file's per-episode
        attributes travel with them. The result equals reading the file and :meth:`add`-ing each
        episode.

        Raises:
          DatasetError: ``path`` is not a dataset file (no ``data`` group) or an episode lacks
            ``num_samples``.
        """
        with h5py.File(path, "r") as src:
            if "data" not in src:
                raise DatasetError(f"{path}: not a dataset file (no 'data' group)")
            names = sorted((k for k in src["data"] if k.startswith("demo_")), key=lambda k: int(k.split("_")[1]))
            for name in names:
                group = src["data"][name]
                if "num_samples" not in group.attrs:
                    raise DatasetError(f"{path}: {name} has no num_samples attribute")
                src.copy(group, self._data, name=f"demo_{self._count}")
                self._count += 1
                self._total += int(group.attrs["num_samples"])
        return len(names)

    def close(self, *, keep: bool = True) -> None:
        """Writes the totals and moves the file into place (``keep=False`` discards it)."""
        if self._file is None:
            return
        info = self._info
        attrs = self._data.attrs
        attrs["env_name"] = info.env_name
        attrs["env_args"] = json.dumps(info.env_args)
        attrs["problem_info"] = json.dumps(info.problem_info)
        attrs["bddl_file_name"] = info.bddl_file_name
        attrs["bddl_file_content"] = info.bddl_file_content
        attrs["macros_image_convention"] = "cv"
        attrs["seg_class_names"] = json.dumps(list(info.seg_class_names))
        attrs["num_demos"] = self._count
        attrs["total"] = self._total
        self._file.close()
        self._file = None
        if keep:
            os.replace(self._partial, self.path)
        else:
            os.remove(self._partial)

    def __enter__(self) -> "DatasetWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close(keep=exc_type is None)


def write_dataset(path: str | os.PathLike, episodes: Iterable[Episode], info: DatasetInfo, *,
                  overwrite: bool = False) -> str:
    """Writes all ``episodes`` to ``path``; returns the path."""
    with DatasetWriter(path, info, overwrite=overwrite) as writer:
        for episode in episodes:
            writer.add(episode)
    return os.fspath(path)


def _attr_str(attrs: Any, name: str) -> str:
    value = attrs.get(name, "")
    return value.decode() if isinstance(value, bytes) else str(value)


def _attr_json(attrs: Any, name: str, where: str) -> Any:
    text = _attr_str(attrs, name)
    if not text:
        return {}
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise DatasetError(f"{where}: attribute {name} is not valid JSON: {err}") from err


def _demo_sort_key(name: str) -> tuple[int, str]:
    suffix = name.rsplit("_", 1)[-1]
    return (int(suffix), name) if suffix.isdigit() else (1 << 30, name)


def _read_episode(grp: h5py.Group, where: str, flip: bool) -> Episode:
    def need(key: str) -> np.ndarray:
        if key not in grp:
            raise DatasetError(f"{where}: missing dataset {key!r}")
        return grp[key][()]

    def maybe(key: str) -> np.ndarray | None:
        return grp[key][()] if key in grp else None

    def image(value: np.ndarray | None) -> np.ndarray | None:
        return value[:, ::-1].copy() if flip and value is not None else value

    rgb = need("obs/agentview_rgb")
    episode = Episode(
        actions=need("actions"),
        states=need("states"),
        rewards=need("rewards"),
        dones=need("dones"),
        agentview_rgb=image(rgb),
        ee_states=need("obs/ee_states"),
        gripper_states=need("obs/gripper_states"),
        joint_states=need("obs/joint_states"),
        eye_in_hand_rgb=image(maybe("obs/eye_in_hand_rgb")),
        agentview_depth=image(maybe("obs/agentview_depth")),
        agentview_seg=image(maybe("obs/agentview_seg")),
        init_state=np.asarray(grp.attrs["init_state"]) if "init_state" in grp.attrs else None,
        model_file=_attr_str(grp.attrs, "model_file"),
        language_instruction=_attr_str(grp.attrs, "language_instruction"),
        executed_actions=maybe("executed_actions"),
        init_split=_attr_str(grp.attrs, "init_split"),
        **{attr: int(grp.attrs[attr]) if attr in grp.attrs else None for attr in _INT_ATTRS},
    )
    episode.validate(where)
    if "num_samples" in grp.attrs and int(grp.attrs["num_samples"]) != episode.num_samples:
        raise DatasetError(
            f"{where}: num_samples attribute says {int(grp.attrs['num_samples'])} but actions has {episode.num_samples}"
        )
    return episode


def read_info(path: str | os.PathLike) -> DatasetInfo:
    """File-level attributes (cheap: reads no arrays)."""
    with _open(path) as f:
        return _info(f, os.fspath(path))


def _open(path: str | os.PathLike) -> h5py.File:
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no dataset file at {path}")
    if not h5py.is_hdf5(path):
        raise DatasetError(f"{path} is not an HDF5 file (corrupt, truncated or another format)")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise DatasetError(f"{path} cannot be opened as HDF5 (truncated or corrupt): {err}") from err
    if "data" not in f:
        f.close()
        raise DatasetError(f"{path} has no 'data' group: not a LIBERO-layout dataset")
    return f


def _info(f: h5py.File, where: str) -> DatasetInfo:
    attrs = f["data"].attrs
    demos = [k for k in f["data"].keys() if k.startswith("demo")]
    return DatasetInfo(
        env_name=_attr_str(attrs, "env_name"),
        env_args=_attr_json(attrs, "env_args", where),
        problem_info=_attr_json(attrs, "problem_info", where),
        bddl_file_name=_attr_str(attrs, "bddl_file_name"),
        bddl_file_content=_attr_str(attrs, "bddl_file_content"),
        seg_class_names=tuple(_attr_json(attrs, "seg_class_names", where) or ()),
        num_demos=int(attrs.get("num_demos", len(demos))),
        total=int(attrs.get("total", 0)),
        image_convention=_attr_str(attrs, "macros_image_convention") or "opengl",
    )


def read_dataset(path: str | os.PathLike, *, demos: Sequence[str] | None = None,
                 flip_opengl: bool = True) -> tuple[DatasetInfo, list[Episode]]:
    """Reads a dataset written here or by LIBERO.

    Args:
      path: the HDF5 file.
      demos: demo group names to read (default: all, in numeric order).
      flip_opengl: flip images of files whose ``macros_image_convention`` is ``"opengl"``
        (LIBERO's) so row 0 is the top. Files without the attribute count as LIBERO's.

    Returns:
      (info, episodes).

    Raises:
      FileNotFoundError: no file. DatasetError: not HDF5, truncated, missing groups or
      datasets, or inconsistent lengths/shapes (the message names the demo and field).
    """
    where = os.fspath(path)
    with _open(path) as f:
        info = _info(f, where)
        names = sorted((k for k in f["data"].keys() if k.startswith("demo")), key=_demo_sort_key)
        if demos is not None:
            missing = sorted(set(demos) - set(names))
            if missing:
                raise DatasetError(f"{where}: no demos {missing}; has {names[:5]}...")
            names = list(demos)
        if not names:
            raise DatasetError(f"{where}: the 'data' group holds no demo_* episodes")
        flip = flip_opengl and info.image_convention == "opengl"
        try:
            episodes = [_read_episode(f["data"][n], f"{where}:data/{n}", flip) for n in names]
        except (OSError, KeyError) as err:
            raise DatasetError(f"{where}: unreadable (truncated or corrupt): {err}") from err
    return info, episodes
