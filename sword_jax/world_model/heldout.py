"""The world model measured while it trains, on fixed segments of held-out and of training episodes.

The training loss is the flow loss of the batch each step trains on, at random noise levels: it says how well the
model fits what it has seen. Two questions it cannot answer decide whether the model is a better simulator:

* Does it predict episodes it never trained on as well as those it did? ``eval_heldout_loss`` against
  ``eval_train_loss`` (the gap grows when the model fits its training segments without generalising).
* Does a better flow loss reach the latents the sampler makes? ``eval_*_sample_error_<n>``: the relative squared
  error of the future latents the flow sampler makes in ``n`` Euler steps from the true context, against the true
  future latents (what one world-model call of a rollout gets wrong). Several ``n`` side by side separate the
  model's error from the sampler's discretisation.
* Does the prediction follow the actions? ``eval_*_other_actions_error_<n>``: the same sample error (at the
  first of the step counts, from the same noise and the same true context) when each segment is given the actions
  of another segment of its batch from its last context frame on (the actions that move its future; a batch's
  segments rolled by one). A model that ignores the actions scores the same with either; the ratio of the two is
  how much of what the model predicts the actions decide, next to how precisely it predicts it.
* Is the sample as detailed as the truth, or the mean of futures the model cannot tell apart?
  ``eval_*_sample_detail_<n>``: the spatial high-frequency energy of the latents sampled in ``n`` steps over the
  true future latents' (:func:`latent_detail`): 1 for samples as detailed as the data, below 1 for a blur (a
  sampler that returns the conditional mean scores a low squared error and a low detail at once).

Each split is ``trainer.eval_batches`` batches of ``data.batch_size`` segments, drawn once from a fixed seed; the
loss uses noise levels spread evenly over the training distribution's quantiles and a fixed noise draw, and the
sampler a fixed initial noise shared by every ``n``. So two evaluations differ only by the weights: the curves are
paired across steps and runs. The weights measured are those inference uses: the EMA where the run keeps one.
Context is the true latents (teacher forcing), never the DLB cache. The training segments come from every training
episode, styled copies included, and the pipeline's held-out episodes are unstyled: read the two curves' trends
(one flattening while the other falls) rather than the level of the gap between them.

A third split, ``policy``, where the held-out file holds it: held-out rollouts of the supervised policy from the
held-out initial states (``data.heldout_policy_rollouts_per_task``), the same scenes as the expert's held-out
episodes acted on by the policy's own sampled actions. It measures what the expert's segments cannot: how well the
model predicts the consequences of the actions a policy takes (GRPO's imagined rollouts are the policy's).
A fourth, ``trainpolicy``, where the training data says which of its episodes are the policy's rollouts
(``sources`` in the latents file): training segments of those alone. Against ``policy`` it separates a model
that has learned what the policy's actions do from one that has learned the rollouts it saw.

A split's figure is a mean over its segments, and a few hard ones can carry it. With ``trainer.eval_segments``
the run's end also measures every fixed segment alone (:meth:`HeldOutEvaluator.per_segment`, from the same noise:
a batch's figure is its segments' energy-weighted mean) and the world-model stage writes them, with each segment's
episode and start, to ``heldout_segments.json``: where in the episodes, and in which episodes, the error lies.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax.sharding import Mesh

from sword_jax import sharding as shd
from sword_jax.rng import stream_key, stream_seed
from sword_jax.world_model import flow, sampler
from sword_jax.world_model.cache_fidelity import latent_distance
from sword_jax.world_model.config import FlowConfig, TrainerConfig
from sword_jax.world_model.data import LatentDataset, SegmentLoader
from sword_jax.world_model.train_state import TrainState

# "trainpolicy" last: the earlier splits keep their batches' noise keys whether or not it is measured
SPLITS = ("train", "heldout", "policy", "trainpolicy")
# what tables and figures call each split
SPLIT_LABELS = {"train": "training", "heldout": "held-out expert", "policy": "held-out policy",
                "trainpolicy": "training policy"}
# the streams of the fixed segments (numpy) and of the fixed noise (JAX) under the run's seed
SEGMENT_STREAM = "world_model/eval_segments"
NOISE_STREAM = "world_model/eval_noise"


def sample_steps(trainer_cfg: TrainerConfig, flow_cfg: FlowConfig) -> tuple[int, ...]:
    """The Euler step counts of the sample error: ``trainer.eval_sample_steps``, or inference's own
    (``flow.sample_steps``) when that is empty."""
    return tuple(trainer_cfg.eval_sample_steps) or (flow_cfg.sample_steps,)


def metric_names(steps: tuple[int, ...], splits: tuple[str, ...] = SPLITS) -> tuple[str, ...]:
    """The names an evaluation reports, per split: its loss, its sample error and detail per step count, then the
    sample error at the first step count under other segments' actions (:func:`make_measure`)."""
    return tuple(f"eval_{split}_{name}" for split in splits
                 for name in ("loss", *(f"sample_error_{n}" for n in steps), *(f"sample_detail_{n}" for n in steps),
                              f"other_actions_error_{steps[0]}"))


def latent_detail(made: jax.Array, future: jax.Array) -> jax.Array:
    """The high-frequency energy of latents ``made [b, n, h, w, c]`` over that of ``future``: the summed squares of
    each latent channel's 4-neighbour Laplacian over the spatial grid (wrapping round, so any grid size counts every
    cell). 1 for latents as detailed as ``future``, below 1 for smoother ones; two flat batches count as alike."""
    def energy(x):
        x = x.astype(jnp.float32)
        lap = 4.0 * x - sum(jnp.roll(x, shift, axis) for shift in (1, -1) for axis in (-3, -2))
        return jnp.sum(jnp.square(lap))

    tiny = jnp.float32(1e-12)
    return (energy(made) + tiny) / (energy(future) + tiny)


def other_actions(actions: jax.Array, num_context: int) -> jax.Array:
    """``actions [b, 1 + 4 (k + p), a]`` of a batch of segments with each segment's actions from its last context
    frame on (the one whose action moves the first future frame, as the learned simulator lays a chunk out) taken
    from the segment before it in the batch (rolled by one); the first frame's and the other context frames'
    actions stay its own."""
    keep = 4 * num_context  # the first frame's action and all but the last context frame's
    return jnp.concatenate([actions[:, :keep], jnp.roll(actions[:, keep:], 1, axis=0)], axis=1)


def fixed_segments(dataset: LatentDataset, count: int, num_context: int, num_future: int,
                   seed: int, among: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(episodes, starts)`` of ``count`` segments drawn uniformly from ``dataset`` (from its episodes ``among``
    where given), a function of ``seed``."""
    num_episodes, num_latents = dataset.shape[:2]
    last_start = num_latents - num_context - num_future
    if last_start < 1:
        raise ValueError(f"held-out evaluation: episodes of {num_latents} latents hold no segment of 1 + "
                         f"{num_context} + {num_future}")
    rng = np.random.default_rng(seed)
    episodes = (rng.integers(0, num_episodes, count) if among is None
                else np.asarray(among)[rng.integers(0, len(among), count)])
    return episodes, rng.integers(1, last_start + 1, count)


def quantile_sigmas(batch: int, cfg: FlowConfig) -> jax.Array:
    """``batch`` noise levels at the midpoints of the training distribution's quantiles
    (:func:`sword_jax.world_model.flow.sample_sigmas` draws ``s ~ U(1/N, 1)``, then shifts it)."""
    low = 1.0 / cfg.num_train_timesteps
    s = low + (1.0 - low) * (jnp.arange(batch, dtype=jnp.float32) + 0.5) / batch
    return flow.shift_sigma(s, cfg.shift)


def segment_errors(made: jax.Array, future: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Per segment of a batch ``[b, n, h, w, c]``: the relative squared error of ``made`` against ``future`` and
    ``future``'s energy (its sum of squares). The batch's ``rel_mse`` (:func:`latent_distance`) is their
    energy-weighted mean."""
    axes = tuple(range(1, future.ndim))
    future = future.astype(jnp.float32)
    energy = jnp.sum(jnp.square(future), axis=axes)
    error = jnp.sum(jnp.square(made.astype(jnp.float32) - future), axis=axes)
    return error / jnp.maximum(energy, jnp.float32(1e-12)), energy


def make_measure(graphdef: nnx.GraphDef, flow_cfg: FlowConfig, num_context: int, steps: tuple[int, ...], *,
                 per_segment: bool = False, with_other_actions: bool = True
                 ) -> Callable[[dict, dict, dict, jax.Array], dict[str, jax.Array]]:
    """``measure(params, buffers, batch, key) -> {"loss", "sample_error_<n>"..., "sample_detail_<n>"...,
    "other_actions_error_<first n>"}`` of one batch of segments (the last under :func:`other_actions`, from the same
    noise; a batch of one segment has no other and scores its own; left out with ``with_other_actions=False``); with
    ``per_segment``, ``{"energy", "sample_error_<n>"...}`` of each segment (``[b]``, :func:`segment_errors`) from the
    same noise."""
    num_cond = 1 + num_context

    def measure(params, buffers, batch, key):
        latents = batch["latents"].astype(jnp.float32)
        actions = batch["actions"].astype(jnp.float32)
        future = latents[:, num_cond:]
        loss_key, sample_key = jax.random.split(key)
        noise = jax.random.normal(loss_key, future.shape, jnp.float32)
        sigma = quantile_sigmas(latents.shape[0], flow_cfg)
        model_input, timesteps = flow.noisy_segment(latents, noise, sigma, num_cond, flow_cfg)
        model_fn = sampler.model_fn_from_state(graphdef, (params, buffers))
        out = ({"energy": segment_errors(future, future)[1]} if per_segment else
               {"loss": flow.flow_loss(model_fn(model_input, timesteps, actions), latents, noise, num_cond, flow_cfg)})
        start = jax.random.normal(sample_key, future.shape, jnp.float32)  # one initial noise for every step count
        for n in steps:
            made = sampler.sample(model_fn, latents[:, :num_cond], actions, key=sample_key,
                                  num_future=future.shape[1], cfg=flow_cfg, num_steps=n, noise=start)
            out[f"sample_error_{n}"] = (segment_errors(made, future)[0] if per_segment
                                        else latent_distance(made, future)["rel_mse"])
            if not per_segment:
                out[f"sample_detail_{n}"] = latent_detail(made, future)
        if with_other_actions and not per_segment:  # the same call under other segments' actions: what they decide
            made = sampler.sample(model_fn, latents[:, :num_cond], other_actions(actions, num_context),
                                  key=sample_key, num_future=future.shape[1], cfg=flow_cfg, num_steps=steps[0],
                                  noise=start)
            out[f"other_actions_error_{steps[0]}"] = latent_distance(made, future)["rel_mse"]
        return out

    return measure


class HeldOutEvaluator:
    """The ``observe`` of the world model's training loop (:func:`sword_jax.train_loop.run_steps`): on the log
    steps where ``trainer.eval_every`` falls (and the last), the fixed segments' loss and sample errors; NaN on
    other log steps (the measurement runs under ``lax.cond``, so they do not pay for it).

    Args:
      graphdef: the world model's static graph.
      flow_cfg, trainer_cfg: the run's flow and trainer settings.
      train, heldout: the training dataset and the held-out episodes' (the same latent layout); without held-out
        episodes (None) only the training segments are measured.
      policy: held-out rollouts of the supervised policy (the same layout), measured as the ``policy`` split;
        None: no such split.
      train_policy: the indices of the training episodes that are the supervised policy's rollouts (or their
        styled copies), measured as the ``trainpolicy`` split: beside ``policy`` it says whether the model
        predicts the policy's rollouts it trained on better than unseen ones. None or empty: no such split.
      loader: the run's segment loader (its shardings and the rows this process holds).
      num_context, num_future: latents per segment.
      mesh, rules: where the model is.
      seed: the run's seed (the segments and the noise are fixed by it).
    """

    def __init__(self, graphdef: nnx.GraphDef, flow_cfg: FlowConfig, trainer_cfg: TrainerConfig, *,
                 train: LatentDataset, heldout: LatentDataset | None, loader: SegmentLoader, num_context: int,
                 num_future: int, mesh: Mesh, rules=shd.DEFAULT_RULES, seed: int,
                 policy: LatentDataset | None = None, train_policy: np.ndarray | None = None):
        among = {}
        if train_policy is not None and len(train_policy):
            among["trainpolicy"] = np.asarray(train_policy)
            if among["trainpolicy"].min() < 0 or among["trainpolicy"].max() >= train.shape[0]:
                raise ValueError(f"held-out evaluation: train_policy indices must lie in [0, {train.shape[0]}), "
                                 f"the training episodes")
        datasets = {"train": train, "heldout": heldout, "policy": policy,
                    "trainpolicy": train if among else None}
        for split, dataset in datasets.items():
            if dataset is not None and (dataset.shape[1:] != train.shape[1:]
                                        or dataset.actions.shape[1:] != train.actions.shape[1:]):
                raise ValueError(f"held-out evaluation: the {split} split's latents {dataset.shape} / actions "
                                 f"{dataset.actions.shape} do not match the training data's {train.shape} / "
                                 f"{train.actions.shape}")
        self.steps = sample_steps(trainer_cfg, flow_cfg)
        splits = tuple(split for split in SPLITS if datasets[split] is not None)
        self.names = metric_names(self.steps, splits)
        self.mesh, self.rules = mesh, rules
        batch_size = loader.sampler.batch_size
        count = trainer_cfg.eval_batches * batch_size
        self.batches, self.segments = {}, {}
        for split in splits:
            dataset = datasets[split]
            episodes, starts = fixed_segments(dataset, count, num_context, num_future,
                                              stream_seed(seed, f"{SEGMENT_STREAM}/{split}"), among.get(split))
            self.segments[split] = (episodes, starts)
            self.batches[split] = [
                loader.place(dataset.segment(episodes[i:i + batch_size][loader.rows],
                                             starts[i:i + batch_size][loader.rows], num_context, num_future))
                for i in range(0, count, batch_size)]
        measure = make_measure(graphdef, flow_cfg, num_context, self.steps)
        every, last = trainer_cfg.eval_every, trainer_cfg.steps
        root = stream_key(jax.random.key(seed), NOISE_STREAM)
        names = self.names

        def evaluate(step, params, buffers, batches):
            def run():
                # every batch of both splits through one traced measurement (lax.map: one batch in memory at once)
                flat = [b for split in splits for b in batches[split]]
                stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *flat)
                keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.arange(len(flat)))
                per = jax.lax.map(lambda bk: measure(params, buffers, bk[0], bk[1]), (stacked, keys))
                count = len(batches[splits[0]])
                return {f"eval_{split}_{name}": jnp.mean(values[i * count:(i + 1) * count]).astype(jnp.float32)
                        for i, split in enumerate(splits) for name, values in per.items()}

            def skip():
                return {name: jnp.float32(jnp.nan) for name in names}

            return jax.lax.cond((step % every == 0) | (step == last), run, skip)

        self._evaluate = jax.jit(evaluate)
        each = make_measure(graphdef, flow_cfg, num_context, self.steps, per_segment=True)

        def per_segment(params, buffers, batches):
            # the evaluation's batches with its keys, so each segment's error is the one its batch's mean holds
            flat = [b for split in splits for b in batches[split]]
            stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *flat)
            keys = jax.vmap(lambda i: jax.random.fold_in(root, i))(jnp.arange(len(flat)))
            per = jax.lax.map(lambda bk: each(params, buffers, bk[0], bk[1]), (stacked, keys))
            count = len(batches[splits[0]])
            return {split: {name: values[i * count:(i + 1) * count] for name, values in per.items()}
                    for i, split in enumerate(splits)}

        # every process gets every segment (in a run of several, each holds only its rows of a batch)
        self._per_segment = jax.jit(per_segment, out_shardings=shd.replicated(mesh))

    def __call__(self, state: TrainState) -> dict[str, jax.Array]:
        """Dispatches the measurement of ``state`` (after ``state.step`` steps); device scalars, NaN off its steps."""
        weights = state.ema_params if state.ema_params is not None else state.params
        with shd.use_mesh(self.mesh, self.rules):
            return self._evaluate(state.step, weights, state.buffers, self.batches)


    def per_segment(self, state: TrainState) -> dict[str, dict[str, list]]:
        """Every fixed segment of every split measured alone with ``state``'s inference weights and the
        evaluation's noise: per split, its ``episodes`` and ``starts`` (the first context latent's index), each
        segment's ``energy`` and ``sample_error_<n>`` (:func:`segment_errors`; the evaluation's figure of a
        batch is their energy-weighted mean). Where a run's error lies (early or late in the episodes, which
        episodes) is read from these. In a run of several processes every process calls it (the segments are
        gathered from the processes that hold them) and gets them all.
        """
        weights = state.ema_params if state.ema_params is not None else state.params
        with shd.use_mesh(self.mesh, self.rules):
            per = jax.device_get(self._per_segment(weights, state.buffers, self.batches))
        out = {}
        for split, values in per.items():
            episodes, starts = self.segments[split]
            row = {"episodes": np.asarray(episodes).tolist(), "starts": np.asarray(starts).tolist()}
            row.update({name: np.asarray(v, np.float64).reshape(-1).tolist() for name, v in values.items()})
            out[split] = row
        return out


def measured(observed: dict | None) -> dict[str, float]:
    """The values of an evaluation the loop read back, without those of log steps it skipped (NaN)."""
    return {k: float(v) for k, v in (observed or {}).items() if math.isfinite(float(v))}
