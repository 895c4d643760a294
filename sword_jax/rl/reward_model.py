"""Success detector: a small CNN scoring each frame in [0, 1] (WoVR's reward model).

Trained with binary cross-entropy on simulator frames labelled by :func:`~sword_jax.rl.data.success_labels`
(``rl.reward_model.labels``: by default the task's success predicate on each frame's state). An imagined
trajectory succeeds once a frame scores at least the threshold (0.9); a chunk's reward is the change
of the score, and the GRPO return follows ``rl.imagined.return_rule`` (by default success alone).
:func:`as_reward_model` wraps trained params in the :class:`~sword_jax.rl.learned_simulator.RewardModel`
protocol.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx, struct
from jaxtyping import Array, Float

from sword_jax import optim
from sword_jax import sharding as shd
from sword_jax.rl.config import RLConfig
from sword_jax.rl.learned_simulator import RewardModel
from sword_jax.rl.policy import resize_frames
from sword_jax.rl.rollout import success_runs


def conv_tower(width: int, rngs: nnx.Rngs) -> nnx.List:
    """Four 3x3 stride-2 convolutions of ``width, 2 width, 4 width, 4 width`` channels (the detector's and the
    value's image encoder; :func:`pooled_features` runs it)."""
    convs, cin = nnx.List(), 3
    for c in (width, 2 * width, 4 * width, 4 * width):
        convs.append(nnx.Conv(cin, c, (3, 3), strides=(2, 2), padding="SAME", rngs=rngs))
        cin = c
    return convs


def pooled_features(convs: nnx.List, frames: Float[Array, "n h w 3"], size: int) -> Float[Array, "n c"]:
    """Frames in [0, 1] resized to ``size``, through :func:`conv_tower` (GELU after each), averaged over space."""
    x = resize_frames(frames, size) * jnp.float32(2.0) - jnp.float32(1.0)
    for conv in convs:
        x = jax.nn.gelu(conv(x))
    return jnp.mean(x, axis=(1, 2))


class SuccessDetector(nnx.Module):
    """Four stride-2 conv blocks -> global average pool -> MLP -> one logit per frame."""

    def __init__(self, cfg: RLConfig, *, rngs: nnx.Rngs):
        self.image_size = cfg.detector_image_size
        w = cfg.reward_model.width
        self.convs = conv_tower(w, rngs)
        self.hidden = nnx.Linear(4 * w, 4 * w, rngs=rngs)
        self.out = nnx.Linear(4 * w, 1, rngs=rngs)

    def __call__(self, frames: Float[Array, "n h w 3"]) -> Float[Array, " n"]:
        """Success logits of frames in [0, 1] (any size; resized to ``cfg.detector_image_size``)."""
        x = pooled_features(self.convs, frames, self.image_size)  # (N, C)
        return self.out(jax.nn.gelu(self.hidden(x)))[:, 0].astype(jnp.float32)


def build_detector(cfg: RLConfig, *, seed: int = 0) -> tuple[nnx.GraphDef, nnx.State]:
    with nnx.use_eager_sharding(False):
        return nnx.split(SuccessDetector(cfg, rngs=nnx.Rngs(seed)))


def load_detector(path: str, rl: RLConfig, *, seed: int = 0) -> tuple[nnx.GraphDef, nnx.State]:
    """``(graphdef, params)`` of the detector saved under ``path`` (``train.train_reward``, the pipeline's
    ``reward_model`` stage), built from ``rl``. Its weights fit any frame size, so the size it was trained on
    (saved with it) is checked against the one ``rl`` reads (:attr:`RLConfig.detector_image_size`).

    Raises:
      ValueError: another kind of checkpoint, another architecture, or another frame size."""
    from sword_jax.rl.params_io import load_params

    graphdef, params = build_detector(rl, seed=seed)
    params, meta = load_params(path, params, kind="reward_model")
    saved = meta.get("rl")
    if isinstance(saved, dict):
        size = (saved.get("reward_model") or {}).get("image_size") or saved.get("image_size")
        if size and int(size) != rl.detector_image_size:
            raise ValueError(f"{path}: the success detector was trained on {size} px frames, this config's reads "
                             f"{rl.detector_image_size} px (rl.reward_model.image_size, else rl.image_size): set it "
                             f"to {size}")
    return graphdef, params


def as_reward_model(graphdef: nnx.GraphDef, params: nnx.State) -> RewardModel:
    """The detector as a per-frame score in [0, 1] (sigmoid of the logit)."""

    def score_fn(params, frames):
        return jax.nn.sigmoid(nnx.merge(graphdef, params)(frames))

    return RewardModel(params=params, score_fn=score_fn)


def threshold_shift(threshold: float, success_threshold: float) -> float:
    """The logit shift that makes the detector's score reach ``success_threshold`` exactly where it reached
    ``threshold`` before (``logit(threshold) - logit(success_threshold)``; thresholds clipped into (0, 1):
    one at or above 1 lets no frame succeed)."""
    eps = 1e-7
    c = min(max(float(threshold), eps), 1.0 - eps)
    t = min(max(float(success_threshold), eps), 1.0 - eps)
    return float(np.log(c / (1.0 - c)) - np.log(t / (1.0 - t)))


def shifted_reward_model(graphdef: nnx.GraphDef, params: nnx.State, shift: float = 0.0) -> RewardModel:
    """The detector with its logit lowered by ``shift`` (:func:`threshold_shift`): a calibrated threshold
    applied under the run's fixed ``rl.success_threshold``. The shift is a leaf of the reward model's
    params, so a new calibration changes an argument of the compiled step, not the program."""

    def score_fn(params, frames):
        return jax.nn.sigmoid(nnx.merge(graphdef, params["net"])(frames) - params["shift"])

    return RewardModel(params={"net": params, "shift": jnp.asarray(shift, jnp.float32)}, score_fn=score_fn)


@struct.dataclass
class DetectorState:
    params: Any
    opt_state: Any
    step: jax.Array  # int32 scalar, steps taken
    first_nonfinite_step: jax.Array  # int32 scalar, 0-based step of the first non-finite loss; -1 = none yet


def make_detector_optimizer(cfg: RLConfig) -> optax.GradientTransformation:
    """AdamW at a constant ``reward_model_learning_rate`` with weight decay 1e-4, no clipping."""
    return optim.make_optimizer(cfg.reward_model.learning_rate, weight_decay=1e-4)


def make_detector_step(graphdef: nnx.GraphDef, cfg: RLConfig, *, mesh=None, rules=shd.DEFAULT_RULES):
    """``init(params) -> state`` and the compiled ``step(state, batch, key) -> (state, metrics)``.

    ``batch = {"frames": [n, H, W, 3] uint8|float, "labels": [n] in {0, 1}}``. Brightness /
    contrast jitter keeps the detector from keying on the world model's colour drift. A
    non-finite loss or gradient skips the update and records the step in
    ``state.first_nonfinite_step``. The step is compiled by :func:`sword_jax.sharding.compile_step`
    over ``mesh`` (default: one device): batch split over its leading dim, state donated.
    """
    optimizer = make_detector_optimizer(cfg)

    def init(params) -> DetectorState:
        return DetectorState(params, optimizer.init(params), jnp.zeros((), jnp.int32), jnp.full((), -1, jnp.int32))

    def step(state: DetectorState, batch, key):
        key = jax.random.fold_in(key, state.step)
        frames = resize_frames(batch["frames"], cfg.detector_image_size)
        gain_key, bias_key = jax.random.split(key)
        n = frames.shape[0]
        gain = jax.random.uniform(gain_key, (n, 1, 1, 1), jnp.float32, 0.8, 1.2)
        bias = jax.random.uniform(bias_key, (n, 1, 1, 1), jnp.float32, -0.1, 0.1)
        frames = jnp.clip(frames * gain + bias, 0.0, 1.0)
        labels = batch["labels"].astype(jnp.float32)

        def loss_fn(params):
            logits = nnx.merge(graphdef, params)(frames)
            loss = jnp.mean(optax.sigmoid_binary_cross_entropy(logits, labels))
            acc = jnp.mean(((logits > 0).astype(jnp.float32) == labels).astype(jnp.float32))
            return loss, acc

        (loss, acc), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
        grad_norm = optax.global_norm(grads)
        # a non-finite loss or gradient skips the update: the last good parameters stay intact
        _, opt_state, params, finite = optim.apply_finite_update(optimizer, loss, grads, state.opt_state, state.params)
        first_nonfinite = jnp.where(~finite & (state.first_nonfinite_step < 0), state.step, state.first_nonfinite_step)
        new_state = DetectorState(params, opt_state, state.step + 1, first_nonfinite.astype(jnp.int32))
        return new_state, {"loss": loss, "accuracy": acc, "grad_norm": grad_norm, "finite": finite.astype(jnp.float32)}

    return init, shd.compile_step(step, shd.default_mesh(mesh), rules)


def train_detector(
    graphdef: nnx.GraphDef,
    params: Any,
    cfg: RLConfig,
    batch_at: Callable[[int], dict],
    *,
    key: jax.Array,
    steps: int | None = None,
    log: Callable[[str], Any] = print,
    checkpoint_dir: str | None = None,
    mesh=None,
    rules=shd.DEFAULT_RULES,
    compiled: tuple[Callable, Callable] | None = None,
) -> tuple[DetectorState, dict[str, Array]]:
    """``steps`` (default ``cfg.reward_model.steps``) detector steps; step ``s`` trains on ``batch_at(s)``.

    ``batch_at`` must be a pure function of the step (e.g. drawn from ``stream_rng(seed, name, s)``):
    with ``checkpoint_dir`` the state is saved every ``cfg.reward_model.checkpoint_every`` steps and
    a rerun resumes from it bit-exactly (see :func:`sword_jax.train_loop.run_steps`). Metrics are
    read one step late on about ten log steps and at the end. ``mesh`` / ``rules``: where the step
    runs (see :func:`make_detector_step`); ``compiled``: its ``(init, step)`` from an earlier call, so
    repeated fine-tunes (:mod:`sword_jax.rl.refresh`) compile once.

    Returns:
      ``(state, metrics)``: the final state and the last step's metrics (empty if no step ran).

    Raises:
      sword_jax.train_loop.NonFiniteLoss: a loss or gradient became non-finite (a
        ``FloatingPointError`` naming the 0-based step; its update was skipped and the last good
        checkpoint is kept).
    """
    from sword_jax.train_loop import run_steps

    steps = cfg.reward_model.steps if steps is None else steps
    init, step = compiled if compiled is not None else make_detector_step(graphdef, cfg, mesh=mesh, rules=rules)

    def report(done: int, metrics: dict[str, float], observed: None, eta: float) -> dict[str, float]:
        del observed, eta
        log(f"reward step {done}/{steps} loss {metrics['loss']:.4f} acc {metrics['accuracy']:.3f}")
        return {"step": done, **metrics}

    run_id = {"rl.reward_model.batch_size": cfg.reward_model.batch_size,
              "rl.reward_model.learning_rate": cfg.reward_model.learning_rate}
    result = run_steps(step, init(params), batch_at, key=key, steps=steps, log_every=max(steps // 10, 1),
                       name="reward model", report=report, checkpoint_dir=checkpoint_dir,
                       checkpoint_every=cfg.reward_model.checkpoint_every, run_id=run_id, log=log)
    return result.state, result.metrics


def detector_report(scores: np.ndarray, episodes: Any, threshold: float, success_frames: int = 1) -> dict[str, float]:
    """How a detector's per-frame scores agree with true success, frame by frame and as the
    imagined-rollout rule reads them (an episode succeeds at the first frame that completes
    ``success_frames`` consecutive frames scoring ``>= threshold``).

    Args:
      scores: ``[E, T]`` detector scores of ``episodes.frames`` (entries past ``lengths`` are ignored).
      episodes: a :class:`~sword_jax.rl.data.EpisodeSet` with ``frame_success``.
      threshold: the success threshold (``rl.success_threshold``).
      success_frames: ``rl.imagined.success_frames``: a frame fires once it ends a run of this many
        frames at or above the threshold (:func:`~sword_jax.rl.rollout.success_runs`), so with more than
        one an isolated spike never fires and the first ``success_frames - 1`` frames of a run do not.

    Returns:
      ``frame_precision``/``frame_recall`` against the success predicate of each frame's state;
      ``episodes_succeeded``/``episodes_failed``; ``fires_on_failed``: share of failed episodes where
      some frame fires (an imagined false success); ``fires_early``: share of succeeded episodes whose
      first firing frame comes more than 4 frames (one latent) before the first solved frame;
      ``mean_lead_frames``: mean of (first solved frame - first firing frame) over succeeded episodes
      that fire; ``misses``: share of succeeded episodes where no frame fires. Episodes that end at
      their success show no solved frame (``success`` set, none in ``frame_success``): they count in
      the frame metrics only, and ``episodes_unobserved`` says how many there were.

    Raises:
      ValueError: episodes without ``frame_success``, scores of the wrong shape or ``success_frames < 1``.
    """
    if success_frames < 1:
        raise ValueError(f"detector_report: success_frames must be >= 1, got {success_frames}")
    if episodes.frame_success is None:
        raise ValueError("detector_report needs episodes.frame_success (per-frame true success)")
    e, t = episodes.frames.shape[:2]
    scores = np.asarray(scores)
    if scores.shape != (e, t):
        raise ValueError(f"detector_report: scores must be [E, T] = {(e, t)}, got {scores.shape}")
    valid = np.arange(t)[None] < episodes.lengths[:, None]
    fire = (scores >= threshold) & valid
    if success_frames > 1:
        fire = np.asarray(success_runs(jnp.asarray(fire))) >= success_frames
    truth = episodes.frame_success & valid
    tp = float((fire & truth).sum())
    first_fire = np.where(fire.any(1), fire.argmax(1), -1)
    shown = truth.any(1)
    solved = np.where(shown, truth.argmax(1), -1)
    ok, failed = shown, ~shown & ~episodes.success
    fired_ok = ok & (first_fire >= 0)
    lead = (solved - first_fire)[fired_ok]
    return {
        "frames": int(valid.sum()), "solved_frames": int(truth.sum()),
        "frame_precision": tp / max(float(fire.sum()), 1.0), "frame_recall": tp / max(float(truth.sum()), 1.0),
        "episodes_succeeded": int(ok.sum()), "episodes_failed": int(failed.sum()),
        "episodes_unobserved": int((~shown & episodes.success).sum()),
        "fires_on_failed": float((first_fire[failed] >= 0).mean()) if failed.any() else None,
        "fires_early": float((lead > 4).sum() / ok.sum()) if ok.any() else None,
        "mean_lead_frames": float(lead.mean()) if lead.size else None,
        "misses": float((first_fire[ok] < 0).mean()) if ok.any() else None,
    }


def score_episodes(score: Callable[[Array], Array], frames: np.ndarray, chunk: int = 256) -> np.ndarray:
    """``[E, T]`` scores of ``[E, T, H, W, 3]`` uint8 frames, ``chunk`` frames per call (the last padded)."""
    e, t = frames.shape[:2]
    flat = frames.reshape((e * t,) + frames.shape[2:])
    out = []
    for i in range(0, len(flat), chunk):
        part = flat[i:i + chunk]
        pad = chunk - len(part)
        if pad:
            part = np.concatenate([part, np.repeat(part[-1:], pad, axis=0)])
        out.append(np.asarray(score(jnp.asarray(part)))[:chunk - pad])
    return np.concatenate(out).reshape(e, t)
