"""GRPO's closed loop in one trained world model, measured without training it: several inference settings side by
side on the same start states, against the policy on MJX's own frames from those starts.

GRPO in the world model trains on what its closed loop pays: the policy acts on the frames the world model
predicts, and from the second decision on the world model predicts from its own earlier frames under those
actions. Measured on ``small``, that loop leaves the real one decision by decision (frame error 0.030 -> 0.095 over
11 decisions from rest) and reality pays the imagined actions about a twentieth of what the same policy earns on
real frames. The runs that measured it (``bench_grpo_reward_source``'s ``exec`` arm) train the policy and evaluate
it on MJX, which costs most of their time; the closed loop itself needs neither. This benchmark measures only the
loop, for each ``--variant`` (an inference setting of the world model: ``flow.*``, e.g. the sampler's starting
noise ``flow.noise_scale``, its Euler steps ``flow.sample_steps`` and their grid ``flow.sample_shift``, action
guidance ``flow.guidance_scale``; or how the start latents are encoded, ``rl.imagined.start_encoding``, the same
keyframes in every variant):

* the policy's imagined rollouts as GRPO's first ``--batches`` steps draw them (their start states and sampling
  keys, at the run's seed; proprio missing, every decision of the horizon run), the same starts
  and keys in every variant, so the variants differ only by the setting;
* their actions executed on MJX from the starts' recorded states (:func:`~sword_jax.rl.imagined_check.execute_observed`):
  what reality paid them (95% Wilson interval) and what the detector said on the same rollouts, with its precision;
* per decision where the closed loop leaves the real one (:func:`~sword_jax.rl.imagined_check.closed_loop_fidelity`,
  over the first ``rl.imagined.fidelity_trajectories`` of each batch, means over the batches): frame error, the
  policy's greedy action gap, both against the real frame a decision earlier, the real motion, the frame's finest
  detail against the real frame's (sharpness: below 1, a blur), and the VAE's floor of frame error, gap and
  sharpness; with ``--probe`` (a state probe: a pipeline's ``probe/probe.npz``) also where the arm, the bowl and
  the gripper of the simulator's frame are against the real frame's as the probe reads both, beside how far they
  moved on the real frames: which part of the imagined scene leaves the real one first;
* how far each variant's start context latents are from the same keyframes encoded from their episodes' first frame
  (``start_context_error``, relative; 0 with ``rl.imagined.start_encoding=prefix``): what the world model was trained
  on, since the latents stage encodes whole episodes;
* each variant against the first, trajectory by trajectory (the same start and keys): the difference of what
  reality paid, with Newcombe's paired interval;
* with ``--frames K``, the first ``K`` trajectories of the first batch drawn decision by decision, the simulator's
  frame above the real frame the same actions reached (``frames_<variant>.png``, the arrays in ``.npz``): what the
  figures above measure, to look at.

And once, ``real``: the same policy from the same starts on MJX's own frames for the same horizon (sampled at
``rl.grpo.temperature``, ``rl.imagined_actions_per_decision`` actions a decision, proprio missing as in the
imagined rollouts): what a simulator faithful to MJX would pay. ::

    python -m benchmarks.bench_closed_loop --pipeline runs/ns/pipeline --policy runs/p/policy_d50.npz \\
        --batches 4 --out runs/ns/closed_loop --variant n1=flow.noise_scale=1 \\
        --variant n05=flow.noise_scale=0.5 --variant n0=flow.noise_scale=0 \\
        --config sword:small --vae.dim_mult=1,4,4 --vae.temporal_downsample=true,true \\
        --rl.imagined.max_chunks=12 --rl.imagined.execute_steps=4 --rl.imagined.keyframe_fraction=0 ...

``--pipeline`` is a ``train.pipeline`` work dir (its ``world_model``, ``vae_run/vae``, ``rl/reward_model`` and
``data/demos.hdf5``); ``--world-model DIR`` measures another world model with them instead of the pipeline's own
(e.g. one trained by ``train.pipeline --adopt`` on the same latents with another training rule). The config and
its overrides are those the pipeline was built with plus GRPO's recipe (the ``exec`` arm's command in
``bench_grpo_reward_source``'s ``commands.json`` without ``train.grpo``'s own flags).
Writes ``closed_loop.json`` to ``--out`` and prints one row per variant. ``--record`` also merges the entry
``world_model_closed_loop_small`` into ``benchmarks/results/latest.json`` (:func:`results_entry`); ``--from
closed_loop.json`` makes that entry from a saved run instead of measuring (no ``--pipeline`` or ``--policy``).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import re
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from sword_jax import cli
from sword_jax.atomic_write import write_json_atomic

VARIANT = re.compile(r"([a-z0-9_]+)=(.+)")
FIGURES = ("frame_error", "action_gap", "frame_error_prev", "action_gap_prev", "motion", "frame_error_vae",
           "action_gap_vae", "ee_cm", "bowl_cm", "gripper_agree", "ee_motion_cm", "bowl_motion_cm", "ee_cm_vae",
           "bowl_cm_vae", "gripper_agree_vae", "sharpness", "sharpness_vae")


def parse_variants(specs: Sequence[str], cfg: Any) -> dict[str, tuple[str, ...]]:
    """``{name: overrides}`` from ``NAME=KEY=VALUE[,KEY=VALUE...]`` specs, each key a ``flow.*`` key that the config
    takes (the settings a simulator is built with) or ``rl.imagined.start_encoding`` (how the same keyframes' start
    latents are encoded); the keyframes, the policy and the detector stay the run's.
    Raises :class:`~sword_jax.cli.UsageError` naming the spec that is refused."""
    from configs.cli import apply_overrides

    out: dict[str, tuple[str, ...]] = {}
    for spec in specs:
        match = VARIANT.fullmatch(spec)
        if not match:
            raise cli.UsageError(f"bench_closed_loop: --variant takes NAME=KEY=VALUE[,KEY=VALUE...] (NAME in a-z, 0-9, "
                                 f"_), got {spec!r}")
        name, body = match.groups()
        if name in out or name == "real":
            raise cli.UsageError(f"bench_closed_loop: --variant {name!r} is given twice or is the reserved name 'real'")
        pairs = tuple(p for p in body.split(",") if p)
        bad = [p for p in pairs if not re.fullmatch(r"(flow\.[a-z_]+|rl\.imagined\.start_encoding)=\S+", p)]
        if bad or not pairs:
            raise cli.UsageError(f"bench_closed_loop: --variant {name}: each setting must be flow.KEY=VALUE (an inference "
                                 f"setting of the world model) or rl.imagined.start_encoding=VALUE (how its start "
                                 f"latents are encoded), got {', '.join(bad) or 'none'}")
        try:
            apply_overrides(cfg, [f"--{p}" for p in pairs]).validate()
        except (ValueError, KeyError, TypeError) as error:
            raise cli.UsageError(f"bench_closed_loop: --variant {name}: {error}") from None
        out[name] = pairs
    if not out:
        raise cli.UsageError("bench_closed_loop: give at least one --variant (e.g. n1=flow.noise_scale=1)")
    return out


def pipeline_inputs(pipeline: str, world_model: str | None = None) -> dict[str, str]:
    """The world model, VAE, detector and demonstrations of a ``train.pipeline`` work dir, or a
    :class:`~sword_jax.cli.UsageError` naming what it lacks. ``world_model``: another run's world model (a
    ``train.pipeline`` work dir, or its ``world_model`` folder) measured with this pipeline's VAE and detector."""
    if world_model and os.path.isdir(os.path.join(world_model, "world_model")):
        world_model = os.path.join(world_model, "world_model")
    paths = {"world_model": world_model or os.path.join(pipeline, "world_model"),
             "vae": os.path.join(pipeline, "vae_run", "vae"),
             "reward": os.path.join(pipeline, "rl", "reward_model"),
             "demos": os.path.join(pipeline, "data", "demos.hdf5")}
    missing = [p for key, p in paths.items() if not (os.path.isfile(p) if key == "demos" else os.path.isdir(p))]
    if missing:
        raise cli.UsageError(f"bench_closed_loop: --pipeline {pipeline} lacks {', '.join(missing)} (a train.pipeline "
                             "work dir built up to its reward_model stage)")
    return paths


def make_measure(graphdef: Any, rl: Any, env: Any, *, read_state: Callable[[jax.Array], jax.Array] | None = None,
                 gripper_closed_below: float = 0.04, keep_frames: int = 0) -> Callable[..., dict[str, jax.Array]]:
    """``measure(params, sim, reward_model, start, env_starts, key)`` for one batch of start states: the imagined
    rollouts (``rl.grpo.group_size`` per start, every decision run), their actions executed in ``env`` from
    ``env_starts``; returns per trajectory ``real`` (reality's verdict) and ``said`` (the detector's), and the
    closed loop's per-decision figures, with ``read_state`` (a state probe, :func:`probe_reader`) the arm's, the
    bowl's and the gripper's too. With ``keep_frames = k`` also ``frames_imagined`` and ``frames_real`` (uint8
    ``[k, C, s, s, 3]`` at the policy's size): per decision the frame the policy read in the simulator and the
    real frame the same actions reached (the start frame at decision 0 in both), of the first ``k`` trajectories.
    Pure; jit it (the simulator is an argument, its settings are its own)."""
    from sword_jax.rl import imagined_check
    from sword_jax.rl.policy import resize_frames
    from sword_jax.rl.rollout import imagined_rollout

    g = rl.grpo.group_size
    if keep_frames < 0:
        raise ValueError(f"make_measure: keep_frames must be >= 0, got {keep_frames}")

    def measure(params, sim, reward_model, start, env_starts, key):
        rollout = imagined_rollout(graphdef, params, sim, reward_model, start, rl, key=key, group_size=g,
                                   stop_on_success=False)
        actions, lengths = imagined_check.executed_actions(rollout, rl.action_bins)
        rows = min(max(rl.imagined.fidelity_trajectories, keep_frames), actions.shape[0])
        env_starts = jnp.repeat(env_starts, g, axis=0)
        if not rows:  # rl.imagined.fidelity_trajectories=0: what reality paid only
            first = imagined_check.execute_open_loop(env, env_starts, actions, lengths)
            return {"real": first >= 0, "said": rollout.success}
        first, frames = imagined_check.execute_observed(env, env_starts, actions, lengths,
                                                        every=rollout.tokens.shape[2], rows=rows)
        round_trip = sim.round_trip if getattr(sim, "round_trip_fn", None) else None
        measured = min(rl.imagined.fidelity_trajectories, actions.shape[0])
        loop = {}
        if measured:  # the figures over the first rl.imagined.fidelity_trajectories, as GRPO's executed step
            loop = imagined_check.closed_loop_fidelity(graphdef, params, rollout, frames[:measured],
                                                       image_size=rl.image_size, action_bins=rl.action_bins,
                                                       round_trip=round_trip, read_state=read_state,
                                                       gripper_closed_below=gripper_closed_below)
        if keep_frames:  # at the policy's size, as uint8: decision d's imagined frame beside the real one
            k = min(keep_frames, rows)
            size = lambda x: resize_frames(x, rl.image_size)  # noqa: E731 - uint8 or [0, 1] -> [0, 1] at its size
            shown = lambda x: jnp.round(255.0 * jnp.clip(x, 0.0, 1.0)).astype(jnp.uint8)  # noqa: E731
            imagined = size(rollout.obs_frames[:k])
            real = jnp.concatenate([imagined[:, :1], size(frames[:k, :-1])], axis=1)
            loop.update(frames_imagined=shown(imagined), frames_real=shown(real))
        return {"real": first >= 0, "said": rollout.success, **loop}

    return measure


def probe_reader(path: str) -> tuple[Callable[[jax.Array], jax.Array], float]:
    """``(read_state, gripper_closed_below)`` of a state probe saved by ``train.train_probe`` (a pipeline's
    ``probe/probe.npz``): frames ``[n, H, W, 3]`` in [0, 1] -> end effector, gripper opening, bowl (metres); or a
    :class:`~sword_jax.cli.UsageError` naming what is wrong with the file."""
    from flax import nnx

    from sword_jax.evaluation import probe

    try:
        graphdef, params, stats, cfg, _ = probe.load_probe(path)
    except (OSError, ValueError, KeyError) as error:
        raise cli.UsageError(f"bench_closed_loop: --probe {path}: {error}") from None
    model = nnx.merge(graphdef, params, stats)
    return (lambda frames: model(probe.resize(frames, cfg.image_size))), cfg.gripper_closed_below


def make_real(graphdef: Any, rl: Any, env: Any, *, max_steps: int) -> Callable[..., jax.Array]:
    """``real(params, start, env_starts, key) -> success [B x G]``: the policy on ``env``'s own frames from the same
    starts, ``rl.imagined_actions_per_decision`` actions a decision, sampled at ``rl.grpo.temperature`` for
    ``max_steps`` actions, reading its missing-proprio input as in the imagined rollouts
    (``rl.imagined.proprio=missing``)."""
    from sword_jax.rl.scan_rollout import scan_rollout

    g = rl.grpo.group_size
    execution = dataclasses.replace(rl, env=dataclasses.replace(rl.env, execute_steps=rl.imagined_actions_per_decision,
                                                                 action_ensemble=False))

    def real(params, start, env_starts, key):
        tokens = jnp.repeat(start.instruction_tokens, g, axis=0)
        valid = jnp.zeros((tokens.shape[0],), jnp.float32)
        rollout, _ = scan_rollout(graphdef, params, env, jnp.repeat(env_starts, g, axis=0), tokens, execution, key=key,
                                  greedy=False, ensemble=False, max_steps=max_steps, proprio_valid=valid)
        return rollout.success

    return real


def start_context_error(batches: Sequence[tuple], exact: Sequence[tuple]) -> float:
    """Mean over the start states of their context latents' relative error (norm of the difference over the norm)
    against ``exact``'s, the same keyframes encoded from their episodes' first frame
    (``rl.imagined.start_encoding=prefix``, the latents the world model was trained on); 0 for those themselves."""
    from benchmarks.bench_start_latents import relative_error

    return float(np.mean(np.concatenate([
        relative_error(np.asarray(start.latents[0])[:, 1:], np.asarray(truth.latents[0])[:, 1:])
        for (start, _), (truth, _) in zip(batches, exact)])))


def rate(outcomes: np.ndarray) -> dict[str, Any]:
    """A success rate with its 95% Wilson interval (:func:`~sword_jax.rl.sim_agreement.wilson_rate`) and its count."""
    from sword_jax.rl.sim_agreement import wilson_rate

    k = int(np.sum(outcomes))
    return {"successes": k, **wilson_rate(k, int(outcomes.size))}


def summarise(name: str, overrides: Sequence[str], batches: list[dict[str, np.ndarray]], decisions: int,
              first: np.ndarray | None) -> dict[str, Any]:
    """One variant's row from its batches' :func:`make_measure` outputs: what reality paid, the detector's verdict
    and precision, the per-decision closed loop (means over the batches) and, against ``first`` (the first
    variant's real verdicts on the same trajectories), the paired difference."""
    from sword_jax.rl.env_rollout import paired_difference_interval

    real = np.concatenate([b["real"] for b in batches]).astype(bool)
    said = np.concatenate([b["said"] for b in batches]).astype(bool)
    row: dict[str, Any] = {"name": name, "overrides": list(overrides), "paid": rate(real), "detector": rate(said),
                           "precision": rate(real[said]) if said.any() else None}
    per_decision = []
    for k in range(1, decisions):
        entry = {"decision": k}
        for what in FIGURES:
            key = f"closed_loop_{what}_{k}"
            if key in batches[0]:
                entry[what] = float(np.mean([b[key] for b in batches]))
        if len(entry) > 1:
            per_decision.append(entry)
    row["decisions"] = per_decision
    if first is not None:
        low, high = paired_difference_interval(first, real)
        row["vs_first"] = {"difference": float(real.mean() - first.mean()), "ci95": [low, high]}
    return row


def line(row: dict[str, Any]) -> str:
    """The printed line of a row."""
    paid = row["paid"]
    text = (f"[closed-loop] {row['name']} ({', '.join(row.get('overrides', ())) or 'the policy on real frames'}): "
            f"reality paid {paid['rate']:.3f} [{paid['ci95'][0]:.3f}, {paid['ci95'][1]:.3f}] of {paid['of']}")
    if "detector" in row:
        text += f", the detector said {row['detector']['rate']:.3f}"
    if "start_context_error" in row:
        text += f", start context {row['start_context_error']:.3f} from training's encoding"
    if row.get("decisions"):
        a, b = row["decisions"][0], row["decisions"][-1]
        text += (f"; frame error {a['frame_error']:.3f} -> {b['frame_error']:.3f}, action gap "
                 f"{a['action_gap']:.3f} -> {b['action_gap']:.3f}")
        if "sharpness" in a:  # the frame's finest detail over the real one's (below 1: a blur)
            text += f", sharpness {a['sharpness']:.2f} -> {b['sharpness']:.2f}"
            if "sharpness_vae" in a:
                text += f" (VAE round trip {a['sharpness_vae']:.2f})"
        if "ee_cm" in a:
            text += (f", arm {a['ee_cm']:.1f} -> {b['ee_cm']:.1f} cm, bowl {a['bowl_cm']:.1f} -> {b['bowl_cm']:.1f} cm, "
                     f"gripper read alike {a['gripper_agree']:.2f} -> {b['gripper_agree']:.2f}")
            if "ee_cm_vae" in a:  # the readouts' floor: the probe on the VAE's round trip of the real frames
                text += (f" (on the VAE's round trip arm {a['ee_cm_vae']:.1f}, bowl {a['bowl_cm_vae']:.1f} cm, "
                         f"gripper {a['gripper_agree_vae']:.2f})")
        text += f" (decisions {a['decision']} -> {b['decision']})"
    if "vs_first" in row:
        v = row["vs_first"]
        text += f"; against the first {100 * v['difference']:+.1f} points [{100 * v['ci95'][0]:+.1f}, {100 * v['ci95'][1]:+.1f}]"
    return text + (f" ({row['seconds']:.0f} s)" if "seconds" in row else "")


def measure_variants(graphdef: Any, params: Any, rl: Any, simulators: dict[str, tuple[Any, Any]],
                     batches: list[tuple] | dict[str, list[tuple]],
                     keys: list[jax.Array], *, env: Any, real_fn: Callable[..., jax.Array] | None = None,
                     overrides: dict[str, Sequence[str]] | None = None, log: Callable[[str], Any] = print,
                     on_row: Callable[[dict[str, Any]], Any] | None = None,
                     read_state: Callable[[jax.Array], jax.Array] | None = None,
                     gripper_closed_below: float = 0.04, start_errors: dict[str, float] | None = None,
                     keep_frames: int = 0, frames_dir: str | None = None) -> dict[str, Any]:
    """Every variant's row (:func:`summarise`) on the same ``batches`` (``(start, env_starts)`` pairs; or per variant
    name its own, the same keyframes encoded its way: ``rl.imagined.start_encoding``) and ``keys``,
    and with ``real_fn`` (:func:`make_real`) the ``real`` row on the same starts; ``on_row(out so far)`` after each
    row (e.g. a run stopped by its time limit keeps the rows measured); ``read_state`` adds the state probe's figures
    (:func:`make_measure`); ``start_errors`` (per variant, :func:`start_context_error`) joins each row as
    ``start_context_error``. With ``keep_frames = k`` and ``frames_dir``, each variant's first ``k`` trajectories of
    the first batch are drawn there, imagined beside real decision by decision (:func:`write_frames`: ``frames_<name>
    .png`` and ``.npz``)."""
    if keep_frames and not frames_dir:
        raise ValueError("measure_variants: keep_frames needs frames_dir (where the frames are drawn)")
    measure = jax.jit(make_measure(graphdef, rl, env, read_state=read_state,
                                   gripper_closed_below=gripper_closed_below, keep_frames=keep_frames))
    if not isinstance(batches, dict):  # the same batches for every variant
        batches = dict.fromkeys(simulators, batches)
    rows, first = [], None
    for name, (sim, reward_model) in simulators.items():
        began = time.perf_counter()
        outs = [jax.device_get(measure(params, sim, reward_model, start, env_starts, key))
                for (start, env_starts), key in zip(batches[name], keys)]
        if keep_frames:  # the first batch's are drawn; no batch's frames go into the row
            shown = [(o.pop("frames_imagined"), o.pop("frames_real")) for o in outs]
            write_frames(os.path.join(frames_dir, f"frames_{name}"), *shown[0])
        row = summarise(name, (overrides or {}).get(name, ()), outs, rl.imagined.max_chunks, first)
        if start_errors and name in start_errors:
            row["start_context_error"] = start_errors[name]
        row["seconds"] = time.perf_counter() - began
        if first is None:
            first = np.concatenate([o["real"] for o in outs]).astype(bool)
        log(line(row))
        rows.append(row)
        if on_row is not None:
            on_row({"variants": rows})
    out: dict[str, Any] = {"variants": rows}
    if real_fn is not None:
        began = time.perf_counter()
        run = jax.jit(real_fn)
        success = np.concatenate([np.asarray(jax.device_get(run(params, start, env_starts, key)))
                                  for (start, env_starts), key in zip(batches[next(iter(simulators))],
                                                                      keys)]).astype(bool)
        out["real"] = {"name": "real", "paid": rate(success), "seconds": time.perf_counter() - began}
        log(line(out["real"]))
        if on_row is not None:
            on_row(out)
    return out


def write_frames(stem: str, imagined: np.ndarray, real: np.ndarray, gap: int = 2) -> str:
    """Draws ``imagined`` and ``real`` (uint8 ``[k, C, s, s, 3]``, :func:`make_measure`'s ``frames_*``) as one image,
    ``stem.png``: per trajectory a row of the simulator's frames (decision 0 to C - 1, left to right) above the real
    frames its actions reached, ``gap`` white pixels between frames and a double gap between trajectories; and both
    arrays as ``stem.npz``. Returns the image's path."""
    import cv2

    imagined, real = np.asarray(imagined, np.uint8), np.asarray(real, np.uint8)
    if imagined.shape != real.shape or imagined.ndim != 5 or imagined.shape[-1] != 3:
        raise ValueError(f"write_frames: imagined {imagined.shape} and real {real.shape} must both be [k, C, s, s, 3]")
    k, c, h, w, _ = imagined.shape
    height, width = k * (2 * h + 3 * gap), c * (w + gap)
    canvas = np.full((height, width, 3), 255, np.uint8)
    for i in range(k):
        for row, frames in enumerate((imagined[i], real[i])):
            top = i * (2 * h + 3 * gap) + row * (h + gap)
            for d in range(c):
                canvas[top:top + h, d * (w + gap):d * (w + gap) + w] = frames[d]
    os.makedirs(os.path.dirname(stem) or ".", exist_ok=True)
    np.savez_compressed(stem + ".npz", imagined=imagined, real=real)
    path = stem + ".png"
    if not cv2.imwrite(path, canvas[..., ::-1]):  # OpenCV writes BGR
        raise OSError(f"write_frames: could not write {path}")
    return path


RECORD_KEY = "world_model_closed_loop_small"


def results_entry(out: dict[str, Any], data: str) -> dict[str, dict[str, Any]]:
    """``{RECORD_KEY: entry}`` from a ``closed_loop.json``: value the first setting's frame error at the last decision
    measured; per setting what reality paid, what the detector said, the share of the real failures it called
    successes, the frame error and greedy action gap at the first and last decisions and the paired difference
    against the first; what the policy earned on MJX's own frames; the run's device, date, command and ``data``
    (the file's path). A file without its date (written before the benchmark stamped it) is refused."""
    if not out.get("variants"):
        raise cli.UsageError(f"bench_closed_loop: {data} holds no measured setting")
    if not out.get("date"):
        raise cli.UsageError(f"bench_closed_loop: {data} holds no date; give the run's date with --date YYYY-MM-DD")
    settings = {}
    for v in out["variants"]:
        paid, said = v["paid"], v["detector"]
        failures = paid["of"] - paid["successes"]
        true = v["precision"]["successes"] if v.get("precision") else 0
        first, last = (v["decisions"][0], v["decisions"][-1]) if v.get("decisions") else ({}, {})
        settings[v["name"]] = {
            "overrides": v["overrides"], "paid": paid["rate"], "paid_ci95": paid["ci95"], "trajectories": paid["of"],
            "detector": said["rate"],
            "false_success_share": (said["successes"] - true) / failures if failures else None,
            "frame_error": [first.get("frame_error"), last.get("frame_error")],
            "action_gap": [first.get("action_gap"), last.get("action_gap")],
            "decisions": [first.get("decision"), last.get("decision")],
            **({"vs_first": v["vs_first"]} if "vs_first" in v else {})}
    reference = settings[out["variants"][0]["name"]]
    entry = {"value": reference["frame_error"][1], "target": None,
             "unit": "mean absolute frame error (in [0, 1]) of the closed loop at its last decision, first setting",
             "device": out.get("device", ""), "date": out["date"], "command": out.get("command", ""), "data": data,
             "settings": settings, "real": out["real"]["paid"]["rate"] if out.get("real") else None,
             "seed": out.get("seed"), "group_size": out.get("group_size"),
             "temperature": out.get("temperature"), "decisions": out.get("decisions")}
    return {RECORD_KEY: entry}


def main(argv: Sequence[str] | None = None) -> dict:
    import configs

    argv = sys.argv[1:] if argv is None else list(argv)
    cfg, rest = configs.from_argv(argv, default="sword:small")
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pipeline", help="a train.pipeline work dir (world model, VAE, detector, demos)")
    parser.add_argument("--world-model", help="the world model measured, a train.pipeline / train_world_model work dir "
                                              "(default: --pipeline's own; e.g. one trained with --adopt on its "
                                              "latents)")
    parser.add_argument("--probe", help="a state probe (train.train_probe; a pipeline's probe/probe.npz): adds per "
                                        "decision where the arm, the bowl and the gripper of the simulator's frame "
                                        "are against the real frame's, read by it")
    parser.add_argument("--policy", help="the policy measured (.npz of bench_policy, or train_policy)")
    parser.add_argument("--variant", action="append", default=[], metavar="NAME=flow.KEY=VALUE[,...]",
                        help="an inference setting of the world model (flow.*) or rl.imagined.start_encoding "
                             "(repeatable; the first is the paired reference)")
    parser.add_argument("--batches", type=int, default=2, help="GRPO steps' start states measured (x rollout batch x G)")
    parser.add_argument("--no-real", action="store_true", help="leave out the policy on MJX's own frames")
    parser.add_argument("--frames", type=int, default=0, metavar="K",
                        help="draw each variant's first K trajectories (first batch) decision by decision, imagined "
                             "above real: --out/frames_<variant>.png and .npz")
    parser.add_argument("--out", help="folder of closed_loop.json")
    parser.add_argument("--record", action="store_true",
                        help=f"merge the entry {RECORD_KEY} into benchmarks/results/latest.json")
    parser.add_argument("--from", dest="source", metavar="CLOSED_LOOP_JSON",
                        help="record a saved run's closed_loop.json instead of measuring (with --record)")
    parser.add_argument("--date", help="with --from: the run's date (YYYY-MM-DD), for a file that does not hold it")
    args = parser.parse_args(rest)
    if args.source:
        return record_saved(args)
    missing = [flag for flag, value in (("--pipeline", args.pipeline), ("--policy", args.policy), ("--out", args.out))
               if not value]
    if missing:
        raise cli.UsageError(f"bench_closed_loop: {', '.join(missing)} required (or --from a saved closed_loop.json)")
    if args.date:
        raise cli.UsageError("bench_closed_loop: --date is for --from (a measured run is stamped with today's date)")
    if args.record and not cfg.name.endswith("-small"):
        raise cli.UsageError(f"bench_closed_loop: --record writes {RECORD_KEY}, a figure of `small`; this run is "
                             f"{cfg.name}")
    if args.batches < 1:
        raise cli.UsageError(f"bench_closed_loop: --batches must be >= 1, got {args.batches}")
    if args.frames < 0:
        raise cli.UsageError(f"bench_closed_loop: --frames must be >= 0 (trajectories drawn), got {args.frames}")
    if cfg.rl.imagined.proprio == "reckoned":
        raise cli.UsageError("bench_closed_loop: rl.imagined.proprio=reckoned is not measured here (the real row reads "
                             "the missing-proprio input); use rl.imagined.proprio=missing")
    if not os.path.exists(args.policy):
        raise cli.UsageError(f"bench_closed_loop: --policy {args.policy}: no such file or folder")
    variants = parse_variants(args.variant, cfg)
    paths = pipeline_inputs(args.pipeline, args.world_model)
    if args.probe and not os.path.isfile(args.probe):
        raise cli.UsageError(f"bench_closed_loop: --probe {args.probe}: no such file")
    read_state, closed_below = probe_reader(args.probe) if args.probe else (None, 0.04)

    from benchmarks.common import device_name
    from configs.cli import apply_overrides
    from sim.dataset import read_dataset
    from sim.mjx_batch import MjxEpisodes
    from sword_jax import sharding as shd
    from sword_jax.load import experiment_vae, experiment_world_model
    from sword_jax.pipeline.grpo import setup_from_weights
    from sword_jax.rl import data as rl_data
    from sword_jax.rl.params_io import load_params
    from sword_jax.rl.policy import build_policy
    from sword_jax.rl.reward_model import load_detector
    from sword_jax.rng import stream_key

    began = time.time()
    rl = cfg.rl
    graphdef, params = build_policy(rl, seed=cfg.seed)
    params, _ = load_params(args.policy, params, kind="policy")
    world_model = experiment_world_model(cfg, paths["world_model"])
    vae = experiment_vae(cfg, paths["vae"], mesh=shd.make_mesh(cfg.mesh))
    detector = load_detector(paths["reward"], rl, seed=cfg.seed)
    episodes = rl_data.load_episodes([paths["demos"]], read=read_dataset)
    if episodes.states is None:
        raise cli.UsageError(f"bench_closed_loop: {paths['demos']} holds no recorded states to execute from")
    root = jax.random.key(cfg.seed)
    starts_key, update_key = stream_key(root, "grpo/starts"), stream_key(root, "grpo/update")
    simulators, batches, exact = {}, {}, None
    for name, pairs in variants.items():
        own = apply_overrides(cfg, [f"--{p}" for p in pairs])
        setup_v = setup_from_weights(own, own.rl, episodes, world_model=world_model, vae=vae, detector=detector)
        simulators[name] = (setup_v.sim, setup_v.reward_model)
        # the same keyframes in every variant (the run's keyframe stream); their latents as the variant encodes them
        batches[name] = [(setup_v.starts(jax.random.fold_in(starts_key, i), i), jnp.asarray(setup_v.env_starts(i)))
                         for i in range(args.batches)]
        if exact is None and own.rl.imagined.start_encoding == "prefix":
            exact = batches[name]  # encoded from their episodes' first frame: what every variant's is measured against
    # the same keyframes encoded from their episodes' first frame: how far each variant's start context is from them
    if exact is None:
        exact_cfg = apply_overrides(cfg, ["--rl.imagined.start_encoding=prefix"])
        exact_setup = setup_from_weights(exact_cfg, exact_cfg.rl, episodes, world_model=world_model, vae=vae,
                                         detector=detector)
        exact = [(exact_setup.starts(jax.random.fold_in(starts_key, i), i), None) for i in range(args.batches)]
    context_errors = {name: start_context_error(own, exact) for name, own in batches.items()}
    keys = [jax.random.fold_in(update_key, i) for i in range(args.batches)]  # GRPO step i's rollout key
    env = MjxEpisodes(cfg.sim, resolution=cfg.sim.resolution)
    horizon = rl.imagined.max_chunks * rl.imagined_actions_per_decision
    real_fn = None if args.no_real else make_real(graphdef, rl, env, max_steps=horizon)
    about = dict(command=" ".join(["python -m benchmarks.bench_closed_loop", *argv]),
                 device=device_name(), seed=cfg.seed, batches=args.batches,
                 date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d"),
                 starts_per_batch=rl.grpo.rollout_batch, group_size=rl.grpo.group_size,
                 decisions=rl.imagined.max_chunks, actions_per_decision=rl.imagined_actions_per_decision,
                 temperature=rl.grpo.temperature, proprio=rl.imagined.proprio)
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "closed_loop.json")

    def save(out):
        write_json_atomic(path, dict(out, **about, seconds=round(time.time() - began, 1)))

    out = measure_variants(graphdef, params, rl, simulators, batches, keys, env=env, real_fn=real_fn,
                           overrides=variants, on_row=save, read_state=read_state, gripper_closed_below=closed_below,
                           start_errors=context_errors, keep_frames=args.frames, frames_dir=args.out)
    save(out)
    if args.record:
        from benchmarks.common import merge_results

        merge_results(results_entry(dict(out, **about), path))
    return dict(out, **about)


def record_saved(args: argparse.Namespace) -> dict:
    """``--from``: a saved ``closed_loop.json``'s rows printed and, with ``--record``, its entry merged into
    ``latest.json``; the options that measure are refused beside it."""
    import json

    given = [flag for flag, value in (("--pipeline", args.pipeline), ("--world-model", args.world_model),
                                      ("--probe", args.probe), ("--policy", args.policy), ("--out", args.out),
                                      ("--variant", args.variant), ("--no-real", args.no_real),
                                      ("--frames", args.frames)) if value]
    if given:
        raise cli.UsageError(f"bench_closed_loop: --from records a saved run; {', '.join(given)} measure one")
    if args.date and not re.fullmatch(r"\d{4}-\d{2}-\d{2}", args.date):
        raise cli.UsageError(f"bench_closed_loop: --date takes YYYY-MM-DD, got {args.date!r}")
    try:
        with open(args.source) as f:
            out = json.load(f)
    except (OSError, ValueError) as error:
        raise cli.UsageError(f"bench_closed_loop: --from {args.source}: {error}") from None
    if not isinstance(out, dict):
        raise cli.UsageError(f"bench_closed_loop: --from {args.source} is not a closed_loop.json")
    if args.date:
        if out.get("date") and out["date"] != args.date:
            raise cli.UsageError(f"bench_closed_loop: {args.source} was measured on {out['date']}, not {args.date}")
        out = dict(out, date=args.date)
    entries = results_entry(out, args.source)
    for row in [*out["variants"], *([out["real"]] if out.get("real") else [])]:
        print(line(row))
    if args.record:
        from benchmarks.common import merge_results

        merge_results(entries)
    return out


if __name__ == "__main__":
    cli.run(main)
