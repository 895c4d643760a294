"""Action-following fidelity: read the simulator state back from frames.

Pixel metrics (LPIPS, FVD) say whether a rollout looks right, not whether it follows the actions.
A small CNN, trained on ground-truth simulator frames, regresses per frame the end-effector
position, the gripper opening and the target bowl's position (all metres). Applied to a world
model's predicted frames and to the ground-truth frames of the same episodes it gives, per frame:

  * ``probe_ee_cm`` / ``probe_bowl_cm``: distance between probe(predicted) and probe(ground truth);
  * ``probe_gripper_agree``: whether both read the gripper as closed (or both as open);
  * ``probe_floor_*``: probe(ground truth) against the true state -- the probe's own error, below
    which the first three cannot be read.

:class:`FidelityScorer` also applies a success detector (the reward model) to both frame sets:
``reward_agree`` (per frame, imagined vs real decision) and precision / recall of the decisions
against true success (the dataset's ``rewards``). This module takes arrays only; extracting the
state from datasets is the caller's job (``train.train_probe``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx, struct
from jaxtyping import Array, Float

from sword_jax import optim
from sword_jax.rng import stream_rng
from sword_jax.train_loop import run_steps

TARGET_NAMES = ("ee_x", "ee_y", "ee_z", "gripper_opening", "bowl_x", "bowl_y", "bowl_z")
EE, GRIPPER, BOWL = slice(0, 3), 3, slice(4, 7)


@dataclasses.dataclass(frozen=True)
class ProbeConfig:
    """The probe network and its training.

    Attributes:
      image_size: frames are resized to this (a power of two >= 8; stride-2 convs down to 4x4).
      width: channels of the first conv (doubling twice).
      steps, batch_size, learning_rate: AdamW training on ground-truth frames.
      gripper_closed_below: opening (m) under which the gripper counts as closed (the Panda opens
        to 0.08 m and closes on the bowl's wall at about 0.003 m).
      seed: initialisation, jitter and batch sampling.
    """

    image_size: int = 64
    width: int = 16
    steps: int = 400
    batch_size: int = 32
    learning_rate: float = 2e-3
    gripper_closed_below: float = 0.04
    seed: int = 0

    def validate(self) -> "ProbeConfig":
        if self.image_size < 8 or self.image_size & (self.image_size - 1):
            raise ValueError(f"probe image_size must be a power of two >= 8, got {self.image_size}")
        if min(self.width, self.steps, self.batch_size) < 1 or not self.learning_rate > 0:
            raise ValueError("probe width, steps, batch_size and learning_rate must be positive")
        return self


class TargetStats(nnx.Variable):
    """Normalisation of the regression targets: fixed from the training data, never trained."""


class StateProbe(nnx.Module):
    """Stride-2 conv blocks down to a 4x4 map -> flatten (keeps where things are) -> MLP -> 7 values."""

    def __init__(self, cfg: ProbeConfig, target_mean: np.ndarray, target_std: np.ndarray, *, rngs: nnx.Rngs):
        self.image_size = cfg.image_size
        self.convs = nnx.List()
        cin = 3
        for i in range(int(math.log2(cfg.image_size // 4))):
            cout = cfg.width * 2 ** min(i, 2)
            self.convs.append(nnx.Conv(cin, cout, (3, 3), strides=(2, 2), padding="SAME", rngs=rngs))
            cin = cout
        self.hidden = nnx.Linear(cin * 16, 8 * cfg.width, rngs=rngs)
        self.out = nnx.Linear(8 * cfg.width, len(TARGET_NAMES), rngs=rngs)
        self.target_mean = TargetStats(jnp.asarray(target_mean, jnp.float32))
        self.target_std = TargetStats(jnp.asarray(target_std, jnp.float32))

    def normalised(self, frames: Float[Array, "n h w 3"]) -> Float[Array, "n 7"]:
        """Standardised predictions of frames in [0, 1] (already at ``image_size``)."""
        x = frames * jnp.float32(2.0) - jnp.float32(1.0)
        for conv in self.convs:
            x = jax.nn.gelu(conv(x))
        x = x.reshape(x.shape[0], -1)  # (N, 16 C)
        return self.out(jax.nn.gelu(self.hidden(x))).astype(jnp.float32)

    def __call__(self, frames: Float[Array, "n h w 3"]) -> Float[Array, "n 7"]:
        """State in metres (``TARGET_NAMES`` order)."""
        return self.normalised(frames) * self.target_std.value + self.target_mean.value


def resize(frames: np.ndarray | Array, size: int) -> Array:
    """Frames (uint8 or [0, 1]) -> float32 [0, 1] at ``size`` x ``size``."""
    frames = jnp.asarray(frames)
    frames = frames.astype(jnp.float32) / jnp.float32(255.0) if frames.dtype == jnp.uint8 else frames.astype(jnp.float32)
    if frames.shape[1:3] == (size, size):
        return frames
    return jax.image.resize(frames, (frames.shape[0], size, size, 3), "linear", antialias=True)


def build_probe(cfg: ProbeConfig, target_mean: np.ndarray, target_std: np.ndarray, *,
                abstract: bool = False) -> tuple[nnx.GraphDef, Any, Any]:
    """``(graphdef, params, stats)`` of a freshly initialised probe (shapes only if ``abstract``).

    Initialised inside one jit: eager initialisation compiles every op on its own.
    """
    make = lambda: StateProbe(cfg, target_mean, target_std, rngs=nnx.Rngs(cfg.seed))
    with nnx.use_eager_sharding(False):
        graphdef, params, stats = nnx.split(nnx.eval_shape(make), nnx.Param, TargetStats)
        if not abstract:
            params, stats = jax.jit(lambda: nnx.split(make(), nnx.Param, TargetStats)[1:])()
    return graphdef, params, stats


@struct.dataclass
class ProbeState:
    params: Any
    stats: Any
    opt_state: Any
    step: jax.Array


def make_probe_step(graphdef: nnx.GraphDef, cfg: ProbeConfig):
    """``init(params, stats) -> state`` and the jitted ``step(state, batch, key) -> (state, metrics)``.

    ``batch = {"frames": [n, S, S, 3] in [0, 1] at cfg.image_size, "targets": [n, 7] metres}``.
    Brightness / contrast jitter keeps the probe from keying on a world model's colour drift. A
    non-finite loss leaves the state unchanged (``metrics["finite"] = 0``).
    """
    schedule = optim.learning_rate_schedule(cfg.learning_rate, kind="cosine", total_steps=cfg.steps, end_fraction=0.05)
    optimizer = optim.make_optimizer(schedule, weight_decay=1e-4)

    def init(params, stats) -> ProbeState:
        return ProbeState(params, stats, optimizer.init(params), jnp.zeros((), jnp.int32))

    def step(state: ProbeState, batch: dict, key: jax.Array) -> tuple[ProbeState, dict]:
        key = jax.random.fold_in(key, state.step)
        gain_key, bias_key = jax.random.split(key)
        frames = batch["frames"].astype(jnp.float32)
        n = frames.shape[0]
        gain = jax.random.uniform(gain_key, (n, 1, 1, 1), jnp.float32, 0.8, 1.2)
        bias = jax.random.uniform(bias_key, (n, 1, 1, 1), jnp.float32, -0.1, 0.1)
        frames = jnp.clip(frames * gain + bias, 0.0, 1.0)

        def loss_fn(params):
            model = nnx.merge(graphdef, params, state.stats)
            target = (batch["targets"].astype(jnp.float32) - model.target_mean.value) / model.target_std.value
            return jnp.mean(jnp.square(model.normalised(frames) - target))

        loss, grads = jax.value_and_grad(loss_fn)(state.params)
        _, opt_state, params, finite = optim.apply_finite_update(optimizer, loss, grads, state.opt_state, state.params)
        new_state = ProbeState(params, state.stats, opt_state, state.step + 1)
        return new_state, {"loss": loss, "grad_norm": optax.global_norm(grads), "finite": finite.astype(jnp.float32)}

    return init, jax.jit(step, donate_argnums=(0,))


def train_probe(frames: np.ndarray, targets: Float[np.ndarray, "n 7"], cfg: ProbeConfig, *,
                progress: Callable[[str], None] = print, checkpoint_dir: str | None = None,
                checkpoint_every: int = 100) -> tuple[nnx.GraphDef, Any, Any, dict]:
    """Trains a probe on ground-truth frames ``[N, H, W, 3]`` (uint8 or [0, 1]) and their state.

    The loop is :func:`sword_jax.train_loop.run_steps`: the batch of step ``s`` is drawn from its own stream
    (``probe/batches``, ``s``), so with ``checkpoint_dir`` a rerun resumes from the last checkpoint (every
    ``checkpoint_every`` steps) and ends bit-identical to an uninterrupted run; a checkpoint of another
    probe (config, its step count included, or training set size) is refused. A non-finite step is skipped
    (its update not applied).

    Returns:
      ``(graphdef, params, stats, metrics)`` with the last step's loss.
    """
    cfg.validate()
    targets = np.asarray(targets, np.float32)
    if frames.shape[0] != targets.shape[0] or targets.shape[1:] != (len(TARGET_NAMES),):
        raise ValueError(f"probe: frames {frames.shape} and targets {targets.shape} must be [N, ...] and [N, 7]")
    # A 1 cm floor on the scale: a target that never moves must not blow up the loss.
    std = np.maximum(targets.std(axis=0), 0.01)
    graphdef, params, stats = build_probe(cfg, targets.mean(axis=0), std)
    small = np.concatenate([np.asarray(_resize_jit(frames[i:i + 256], cfg.image_size))
                            for i in range(0, len(frames), 256)])
    small = (small * 255.0 + 0.5).astype(np.uint8)  # the training set at probe size, on the host
    init, step = make_probe_step(graphdef, cfg)

    def batch_at(i: int) -> dict[str, np.ndarray]:
        idx = stream_rng(cfg.seed, "probe/batches", i).integers(0, len(small), cfg.batch_size)
        return {"frames": small[idx].astype(np.float32) / np.float32(255.0), "targets": targets[idx]}

    def report(done: int, metrics: dict[str, float], _: Any, eta: float) -> dict[str, float]:
        progress(f"[probe] step {done}/{cfg.steps} loss {metrics['loss']:.4f}")
        return {"step": done, **metrics}

    run_id = {**dataclasses.asdict(cfg), "train_frames": int(len(small))}  # steps too: they shape the schedule
    result = run_steps(step, init(params, stats), batch_at, key=jax.random.key(cfg.seed), steps=cfg.steps,
                       log_every=max(cfg.steps // 5, 1), name="probe", report=report, checkpoint_dir=checkpoint_dir,
                       checkpoint_every=checkpoint_every, run_id=run_id, log=progress, on_nonfinite="skip")
    metrics = result.history[-1] if result.history else {}
    return graphdef, result.state.params, result.state.stats, {k: float(v) for k, v in metrics.items() if k != "step"}


@functools.partial(jax.jit, static_argnums=1)
def _resize_jit(frames, size: int):
    return resize(frames, size)


@functools.lru_cache(maxsize=8)
def _predict_fn(graphdef: nnx.GraphDef, image_size: int):
    return jax.jit(lambda params, stats, frames: nnx.merge(graphdef, params, stats)(resize(frames, image_size)))


def predict(graphdef: nnx.GraphDef, params: Any, stats: Any, frames: np.ndarray, *, image_size: int,
            batch_size: int = 256) -> Float[np.ndarray, "n 7"]:
    """Probe readout (metres, ``TARGET_NAMES`` order) of frames ``[N, H, W, 3]`` (uint8 or [0, 1])."""
    run = _predict_fn(graphdef, image_size)
    return np.concatenate([np.asarray(run(params, stats, frames[i:i + batch_size]))
                           for i in range(0, len(frames), batch_size)]) if len(frames) else np.zeros((0, 7), np.float32)


def save_probe(path: str, params: Any, stats: Any, cfg: ProbeConfig, **meta: Any) -> str:
    """Writes the probe to ``path`` (``.npz``: leaves in tree order, config and ``meta`` as JSON)."""
    leaves = jax.tree.leaves((params, stats))
    np.savez(path, config=json.dumps({"probe": dataclasses.asdict(cfg), "targets": TARGET_NAMES, **meta}),
             **{f"leaf_{i:04d}": np.asarray(leaf) for i, leaf in enumerate(leaves)})
    return path


def load_probe(path: str) -> tuple[nnx.GraphDef, Any, Any, ProbeConfig, dict]:
    """``(graphdef, params, stats, cfg, meta)`` of a probe written by :func:`save_probe`."""
    with np.load(path) as data:
        meta = json.loads(str(data["config"]))
        leaves = [data[f"leaf_{i:04d}"] for i in range(sum(k.startswith("leaf_") for k in data.files))]
    if tuple(meta.get("targets", ())) != TARGET_NAMES:
        raise ValueError(f"{path}: probe targets {meta.get('targets')} != {TARGET_NAMES}")
    cfg = ProbeConfig(**meta.pop("probe"))
    graphdef, params, stats = build_probe(cfg, np.zeros(len(TARGET_NAMES)), np.ones(len(TARGET_NAMES)), abstract=True)
    fresh, treedef = jax.tree.flatten((params, stats))
    if [x.shape for x in fresh] != [x.shape for x in leaves]:
        raise ValueError(f"{path}: stored probe does not match its config {cfg}")
    params, stats = jax.tree.unflatten(treedef, [jnp.asarray(x) for x in leaves])
    return graphdef, params, stats, cfg, meta


@dataclasses.dataclass(frozen=True)
class FidelityScorer:
    """Action-following metrics of predicted vs ground-truth videos (see the module docstring).

    Attributes:
      probe: frames ``[N, H, W, 3]`` in [0, 1] -> state ``[N, 7]`` (metres), or None.
      success_score: frames -> success score ``[N]`` in [0, 1] (the reward model), or None.
      success_threshold: score above which a frame counts as success.
      gripper_closed_below: gripper opening (m) under which it counts as closed.
    """

    probe: Callable[[np.ndarray], np.ndarray] | None = None
    success_score: Callable[[np.ndarray], np.ndarray] | None = None
    success_threshold: float = 0.9
    gripper_closed_below: float = 0.04

    @classmethod
    def from_probe_file(cls, path: str, **kwargs) -> "FidelityScorer":
        graphdef, params, stats, cfg, _ = load_probe(path)
        run = functools.partial(predict, graphdef, params, stats, image_size=cfg.image_size)
        return cls(probe=run, gripper_closed_below=cfg.gripper_closed_below, **kwargs)

    def score(self, gt: Float[np.ndarray, "b t h w 3"], pred: Float[np.ndarray, "b t h w 3"], *,
              targets: Float[np.ndarray, "b t 7"] | None = None,
              rewards: Float[np.ndarray, "b t"] | None = None) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        """Per-frame ``{name: [B, T]}`` metrics and scalar-only ``{name: value}`` ones.

        Args:
          gt, pred: scored frames in [0, 1].
          targets: true state of the ground-truth frames (``TARGET_NAMES``), for the probe's floor.
          rewards: true success per frame (> 0 = success), for the detector's precision / recall.
        """
        b, t = gt.shape[:2]
        per_frame: dict[str, np.ndarray] = {}
        scalars: dict[str, float] = {}
        flat = lambda video: video.reshape(b * t, *video.shape[2:])
        if self.probe is not None:
            state_gt = np.asarray(self.probe(flat(gt))).reshape(b, t, -1)
            state_pred = np.asarray(self.probe(flat(pred))).reshape(b, t, -1)
            per_frame.update(self._compare_states(state_pred, state_gt, "probe"))
            if targets is not None:
                per_frame.update(self._compare_states(state_gt, np.asarray(targets, np.float32), "probe_floor"))
        if self.success_score is not None:
            real = np.asarray(self.success_score(flat(gt))).reshape(b, t) > self.success_threshold
            imagined = np.asarray(self.success_score(flat(pred))).reshape(b, t) > self.success_threshold
            per_frame["reward_agree"] = (real == imagined).astype(np.float64)
            scalars["reward_episode_agree"] = float(np.mean(real.any(axis=1) == imagined.any(axis=1)))
            if rewards is not None:
                truth = np.asarray(rewards) > 0
                scalars["reward_true_success_share"] = float(truth.mean())
                for prefix, decided in (("reward", imagined), ("reward_floor", real)):
                    scalars.update(_precision_recall(decided, truth, prefix))
        return per_frame, scalars

    def _compare_states(self, state: np.ndarray, reference: np.ndarray, prefix: str) -> dict[str, np.ndarray]:
        closed = lambda s: s[..., GRIPPER] < self.gripper_closed_below
        return {
            f"{prefix}_ee_cm": 100.0 * np.linalg.norm(state[..., EE] - reference[..., EE], axis=-1),
            f"{prefix}_bowl_cm": 100.0 * np.linalg.norm(state[..., BOWL] - reference[..., BOWL], axis=-1),
            f"{prefix}_gripper_agree": (closed(state) == closed(reference)).astype(np.float64),
        }


def _precision_recall(decided: np.ndarray, truth: np.ndarray, prefix: str) -> dict[str, float]:
    """Frame-level precision / recall of success decisions; a ratio with no denominator is left out."""
    out = {}
    if decided.any():
        out[f"{prefix}_precision"] = float((decided & truth).sum() / decided.sum())
    if truth.any():
        out[f"{prefix}_recall"] = float((decided & truth).sum() / truth.sum())
    return out
