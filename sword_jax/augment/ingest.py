"""Ingest episodes styled elsewhere (e.g. by a generative style-transfer model run offline).

Accepted layouts (frames uint8 [0, 255], or float in [0, 1] or [-1, 1]; see ``frames_range``):

* ``.npz``: either stacked ``episode_ids [N]`` + ``frames [N, T, H, W, 3]`` (+ optional
  ``actions [N, T, A]``), or one ``episode_<id>`` array ``[T, H, W, 3]`` per episode (+ optional
  ``episode_<id>_actions``);
* ``.h5`` / ``.hdf5``: ``episodes/<id>/frames`` ``[T, H, W, 3]`` (+ optional ``episodes/<id>/actions``);
* a directory: ``<dir>/<id>/<frame index>.png`` (indices 0..T-1, any zero padding; + optional
  ``<dir>/<id>/actions.npy``).

Every styled episode is aligned with its original by episode id: the frame count and image
size must match, and actions, when the styled file carries them, must equal the original's.
Depth, segmentation and actions of the result come from the originals (a style transfer
changes appearance only).
"""

from __future__ import annotations

import os
import re

import numpy as np

from sword_jax.augment.episodes import Episodes, as_episodes

_EPISODE_KEY = re.compile(r"^episode_(-?\d+)$")


class StyledEpisodeError(ValueError):
    """A styled file is unreadable or does not align with its original episode."""


def _to_unit(frames: np.ndarray, frames_range: str, where: str) -> np.ndarray:
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise StyledEpisodeError(f"{where}: frames must be [T, H, W, 3], got {frames.shape}")
    if np.issubdtype(frames.dtype, np.floating) and not np.isfinite(frames).all():
        raise StyledEpisodeError(f"{where}: frames contain NaN/inf")
    if frames_range == "auto":
        if frames.dtype == np.uint8:
            frames_range = "uint8"
        elif np.issubdtype(frames.dtype, np.floating):
            frames_range = "signed" if frames.min() < -1e-3 else "unit"
        else:
            raise StyledEpisodeError(f"{where}: frames dtype {frames.dtype} is neither uint8 nor float")
    if frames_range == "uint8":
        out = frames.astype(np.float32) / 255.0
    elif frames_range == "signed":
        out = (frames.astype(np.float32) + 1.0) * 0.5
    elif frames_range == "unit":
        out = frames.astype(np.float32)
    else:
        raise ValueError(f"frames_range must be auto|uint8|signed|unit, got {frames_range!r}")
    if not np.isfinite(out).all():
        raise StyledEpisodeError(f"{where}: frames contain NaN/inf")
    if out.min() < -1e-3 or out.max() > 1 + 1e-3:
        raise StyledEpisodeError(f"{where}: frames outside the {frames_range} range")
    return np.clip(out, 0.0, 1.0)


def _read_npz(path: str) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
    with np.load(path, allow_pickle=False) as data:
        keys = set(data.files)
        if "frames" in keys:
            if "episode_ids" not in keys:
                raise StyledEpisodeError(f"{path}: stacked 'frames' needs 'episode_ids'")
            ids, frames = data["episode_ids"], data["frames"]
            actions = data["actions"] if "actions" in keys else None
            if frames.ndim != 5 or len(ids) != len(frames) or (actions is not None and len(actions) != len(ids)):
                raise StyledEpisodeError(
                    f"{path}: episode_ids {ids.shape}, frames {frames.shape} (want [N, T, H, W, 3])"
                    + ("" if actions is None else f", actions {actions.shape}") + " do not line up"
                )
            return {int(i): (frames[k], None if actions is None else actions[k]) for k, i in enumerate(ids)}
        out = {}
        for key in keys:
            match = _EPISODE_KEY.match(key)
            if match:
                actions_key = f"{key}_actions"
                out[int(match.group(1))] = (data[key], data[actions_key] if actions_key in keys else None)
        if not out:
            raise StyledEpisodeError(f"{path}: no 'frames'/'episode_ids' nor 'episode_<id>' arrays (keys: {sorted(keys)[:10]})")
        return out


def _read_hdf5(path: str) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        if "episodes" not in f:
            raise StyledEpisodeError(f"{path}: no 'episodes' group (want episodes/<id>/frames)")
        for name, group in f["episodes"].items():
            if not name.lstrip("-").isdigit():
                raise StyledEpisodeError(f"{path}: episodes/{name}: group names must be integer episode ids")
            if "frames" not in group:
                raise StyledEpisodeError(f"{path}: episodes/{name} has no 'frames'")
            out[int(name)] = (group["frames"][()], group["actions"][()] if "actions" in group else None)
    return out


def _read_png_dir(path: str) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
    import cv2

    out = {}
    for name in sorted(os.listdir(path)):
        episode_dir = os.path.join(path, name)
        if not os.path.isdir(episode_dir):
            continue
        if not name.lstrip("-").isdigit():
            raise StyledEpisodeError(f"{episode_dir}: episode directories must be named by integer id")
        pngs = {}
        for file in os.listdir(episode_dir):
            stem, ext = os.path.splitext(file)
            if ext.lower() == ".png":
                if not stem.isdigit():
                    raise StyledEpisodeError(f"{episode_dir}/{file}: PNG names must be frame indices")
                pngs[int(stem)] = os.path.join(episode_dir, file)
        if sorted(pngs) != list(range(len(pngs))) or not pngs:
            missing = sorted(set(range(max(pngs, default=-1) + 1)) - set(pngs))
            raise StyledEpisodeError(f"{episode_dir}: frames must be numbered 0..T-1 (missing {missing[:10]})")
        frames = []
        for index in range(len(pngs)):
            image = cv2.imread(pngs[index], cv2.IMREAD_COLOR)
            if image is None:
                raise StyledEpisodeError(f"{pngs[index]}: unreadable or corrupt PNG")
            frames.append(image[..., ::-1])  # BGR -> RGB
        shapes = {f.shape for f in frames}
        if len(shapes) != 1:
            raise StyledEpisodeError(f"{episode_dir}: frames of different sizes {sorted(shapes)}")
        actions_path = os.path.join(episode_dir, "actions.npy")
        actions = np.load(actions_path, allow_pickle=False) if os.path.exists(actions_path) else None
        out[int(name)] = (np.stack(frames), actions)
    if not out:
        raise StyledEpisodeError(f"{path}: no episode directories")
    return out


def read_styled(path: str) -> dict[int, tuple[np.ndarray, np.ndarray | None]]:
    """``{episode_id: (frames [T, H, W, 3] as stored, actions or None)}`` from any accepted layout."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"styled episodes: {path} does not exist")
    try:
        if os.path.isdir(path):
            return _read_png_dir(path)
        ext = os.path.splitext(path)[1].lower()
        if ext == ".npz":
            return _read_npz(path)
        if ext in (".h5", ".hdf5"):
            return _read_hdf5(path)
    except StyledEpisodeError:
        raise
    except (OSError, ValueError, KeyError) as err:  # zip / hdf5 / pickle errors of corrupt files
        raise StyledEpisodeError(f"{path}: cannot read styled episodes ({type(err).__name__}: {err})") from err
    raise StyledEpisodeError(f"{path}: unknown format (want .npz, .h5/.hdf5 or a directory of PNGs)")


def load_styled_episodes(
    path: str,
    originals: Episodes | dict,
    *,
    frames_range: str = "auto",
    require_all: bool = False,
    action_atol: float = 1e-5,
) -> Episodes:
    """Styled episodes aligned with their originals (sorted by id).

    Args:
      path: a file or directory in one of the module's layouts.
      originals: the raw episodes (``episode_ids`` must cover every styled id).
      frames_range: "auto" (uint8 -> [0, 255]; float with negatives -> [-1, 1]; else [0, 1]),
        or "uint8" | "signed" | "unit".
      require_all: every original must have a styled version.
      action_atol: tolerance when the styled file carries actions.

    Returns:
      :class:`Episodes` with the styled frames in [0, 1] and the originals' depth, seg, actions.

    Raises:
      StyledEpisodeError: unreadable files, unknown ids, frame-count / size / action mismatches.
    """
    orig = as_episodes(originals, require_geometry=False)
    styled = read_styled(path)
    position = {int(i): k for k, i in enumerate(orig.episode_ids)}
    unknown = sorted(set(styled) - set(position))
    if unknown:
        raise StyledEpisodeError(f"{path}: styled episodes {unknown[:10]} have no original (ids {sorted(position)[:10]}...)")
    if require_all:
        missing = sorted(set(position) - set(styled))
        if missing:
            raise StyledEpisodeError(f"{path}: originals {missing[:10]} have no styled version")
    ids = np.array(sorted(styled), np.int64)
    index = np.array([position[int(i)] for i in ids], np.int64)
    frames = []
    for episode_id, k in zip(ids, index):
        raw_frames, actions = styled[int(episode_id)]
        where = f"{path}: episode {episode_id}"
        unit = _to_unit(np.asarray(raw_frames), frames_range, where)
        expected = orig.frames.shape[1:]
        if unit.shape[0] != expected[0]:
            raise StyledEpisodeError(f"{where}: {unit.shape[0]} frames, the original has {expected[0]}")
        if unit.shape[1:] != expected[1:]:
            raise StyledEpisodeError(f"{where}: frames are {unit.shape[1:3]}, the original's are {expected[1:3]}")
        if actions is not None:
            actions = np.asarray(actions, np.float32)
            if actions.shape != orig.actions.shape[1:] or not np.allclose(actions, orig.actions[k], atol=action_atol):
                raise StyledEpisodeError(f"{where}: actions differ from the original's (shape {actions.shape} vs "
                                         f"{orig.actions.shape[1:]})")
        frames.append(unit)
    aligned = orig.take(index)
    return aligned._replace(frames=np.stack(frames))
