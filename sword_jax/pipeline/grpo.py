"""GRPO's orchestration: the learned simulator's setup, the evaluation points beside the success, the
replay of real episodes in the learned simulator, and the run in it (``python -m train.grpo`` is the
command line; GRPO in the ground-truth environments is :mod:`sim.grpo_env`).

Nothing here imports a simulator: demonstrations arrive as an ``rl.data.EpisodeSet``, the ground-truth
evaluation as ``evaluate_in_sim``'s keyword arguments.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from sword_jax import sharding as shd
from sword_jax.rl import data as rl_data
from sword_jax.rl import grpo, sim_agreement
from sword_jax.rl.env_rollout import make_act_fns
from sword_jax.rl.grpo_loop import grpo_run_id, read_history, train_grpo
from sword_jax.rl.learned_simulator import StartState, toy_reward_model, toy_simulator, toy_start_states
from sword_jax.rl.policy import tokenize_instructions
from sword_jax.rl.policy_success import evaluate_in_sim
from sword_jax.rl.reward_model import as_reward_model, load_detector
from sword_jax.rl.rollout import expand_groups, imagined_rollout
from sword_jax.rng import stream_key, stream_rng

log = functools.partial(print, flush=True)


@dataclasses.dataclass(frozen=True)
class GRPOInputs:
    """The checkpoints and demonstrations GRPO starts from (``--simulator world_model`` needs
    ``world_model``, ``reward`` and ``demos``; ``env`` reads ``demos`` only to fit the proprio reckoning
    or, with ``rl.env.starts=keyframes``, to start from their recorded states)."""

    demos: tuple[str, ...] = ()  # LIBERO-layout HDF5 whose frames are the start keyframes
    world_model: str = ""  # train_world_model work dir
    vae: str = ""  # VAE checkpoint directory (train_vae)
    policy: str = ""  # SFT policy checkpoint (train_policy); empty: from scratch
    reward: str = ""  # reward model checkpoint (train_reward)
    latents: str = ""  # the world model's training latents (.npz): what a refresh fine-tunes it on besides
    light_decoder: str = ""  # the light rollout decoder (train_light_decoder); rl.imagined.decoder=light needs it




class Setup(NamedTuple):
    """What a GRPO run in a learned simulator needs: the simulator and reward model, ``starts(key, step,
    rows=None)`` (a step's ``rl.imagined_starts_per_step`` start states -- ``rl.grpo.rollout_batch`` times
    ``rl.imagined.oversample``; with ``rows``, only those rows of them, each the same whichever rows are
    asked for), the toy's fixed evaluation starts, the real history's encoder (for replays) and
    ``env_starts(step, rows=None)``: the recorded simulator states of the same start states (keyframes of
    episodes with ``states``), what ``rl.imagined.reward=executed`` resets the real environment to, and
    ``start_steps(step, rows=None)``: each of those start states' step in its episode (the keyframe's index),
    by which an executed step counts its outcomes, and ``windows(step, rows=None)``: the same keyframes' real
    windows (:func:`~sword_jax.rl.data.keyframe_window`: first frame, history, actions), which ``starts`` encodes.
    ``encode_prefix(prefix, latent_index)``: with ``rl.imagined.start_encoding=prefix`` the prefix encoder
    (:func:`~sword_jax.rl.world_model_sim.encode_prefix`) every other path that encodes starts from real frames
    (replays, refreshes, the closed loop) uses in place of ``encode``, and ``windows`` carry the prefix; None with
    ``window``."""

    sim: Any
    reward_model: Any
    starts: Callable[..., StartState]
    eval_start: StartState | None = None
    encode: Callable[..., Any] | None = None
    env_starts: Callable[..., np.ndarray] | None = None
    start_steps: Callable[..., np.ndarray] | None = None
    windows: Callable[..., dict] | None = None
    encode_prefix: Callable[..., Any] | None = None


def toy_setup(cfg, rl) -> Setup:
    """The analytic toy simulator and reward (no checkpoints): a smoke run of the whole GRPO path."""
    size = rl.image_size
    sim, reward_model = toy_simulator(frame_size=size, chunk_len=rl.chunk_len, proprio_dim=rl.proprio_dim), toy_reward_model()
    texts = [f"reach the goal of task {t}" for t in range(max(len(cfg.sim.tasks), 2))]
    tokens = jnp.asarray(tokenize_instructions(texts, rl.policy.max_instruction_bytes))

    def starts(key, step, rows=None):
        del step  # the key is already a function of the step
        pick = jax.random.randint(key, (rl.imagined_starts_per_step,), 0, tokens.shape[0])
        return toy_start_states(tokens[pick], key=key, frame_size=size, proprio_dim=rl.proprio_dim, rows=rows)

    eval_key = stream_key(jax.random.key(cfg.seed), "grpo/toy_eval_starts")
    eval_start = expand_groups(toy_start_states(jnp.tile(tokens, (4, 1)), key=eval_key, frame_size=size,
                                                proprio_dim=rl.proprio_dim), 2)
    return Setup(sim, reward_model, starts, eval_start)


def world_model_setup(cfg, rl, inputs: GRPOInputs, episodes, *, reckoning=None) -> Setup:
    """The learned simulator (world model + VAE), the reward model and keyframe starts from ``episodes``
    (an ``rl.data.EpisodeSet`` of the demonstrations); ``reckoning``: the proprio ReckoningConfig when
    ``rl.imagined.proprio=reckoned`` (the simulator's action convention, fitted to the demonstrations).
    The weights are read from ``inputs``, then set up by :func:`setup_from_weights`."""
    from sword_jax.load import experiment_vae, experiment_world_model, load_light_decoder

    if rl.imagined.proprio == "reckoned" and rl.proprio_dim != 8:
        raise ValueError(f"rl.imagined.proprio=reckoned integrates the simulator's 8-D proprio; got rl.proprio_dim="
                         f"{rl.proprio_dim} (use --rl.imagined.proprio=missing)")
    if rl.imagined.proprio == "reckoned" and reckoning is None:
        raise ValueError("rl.imagined.proprio=reckoned needs the action convention (reckoning)")
    light_decoder = None
    if rl.imagined.decoder == "light":
        if not inputs.light_decoder:
            raise ValueError("rl.imagined.decoder=light needs the light decoder the pipeline's light_decoder stage trains "
                             "(train.grpo --light-decoder DIR; train.train_light_decoder makes one)")
        light_graphdef, light_state, _ = load_light_decoder(
            inputs.light_decoder, z_dim=cfg.vae.z_dim, latent_size=cfg.data.image_size // cfg.vae.spatial_factor,
            temporal_factor=cfg.vae.temporal_factor)
        light_decoder = (light_graphdef, light_state)
    world_model = experiment_world_model(cfg, inputs.world_model)
    vae = experiment_vae(cfg, inputs.vae, mesh=shd.make_mesh(cfg.mesh))  # beside the world model
    det_graphdef, det_params = load_detector(inputs.reward, rl, seed=cfg.seed)
    if rl.imagined.eval_replay_episodes and cfg.sim.resolution != cfg.data.image_size:
        raise ValueError(f"rl.imagined.eval_replay_episodes replays real episodes rendered at sim.resolution="
                         f"{cfg.sim.resolution} in a world model of data.image_size={cfg.data.image_size}; make them "
                         "equal or pass --rl.imagined.eval_replay_episodes=0")
    return setup_from_weights(cfg, rl, episodes, world_model=world_model, vae=vae,
                              detector=(det_graphdef, det_params), light_decoder=light_decoder, reckoning=reckoning)


def setup_from_weights(cfg, rl, episodes, *, world_model: tuple[Any, Any], vae: tuple[Any, Any],
                       detector: tuple[Any, Any], light_decoder: tuple[Any, Any] | None = None,
                       reckoning=None) -> Setup:
    """:func:`world_model_setup` from weights in hand: ``world_model``, ``vae``, ``detector`` (the success
    detector) and ``light_decoder`` as ``(graphdef, state)`` pairs, loaded or (``benchmarks.bench_grpo_step``)
    freshly initialised. The simulator is built at ``rl.imagined.sim_precision``, with the light decoder when
    one is given; the start states are keyframes of ``episodes`` encoded by the VAE."""
    from sword_jax.rl.sim_builder import build_simulator
    from sword_jax.rl.world_model_sim import encode_history, encode_prefix

    wm_graphdef, wm_state = world_model
    vae_graphdef, vae_state = vae
    # the world model's geometry is the config's (ExperimentConfig.validate checks rl against it)
    tf = cfg.vae.temporal_factor  # frames per latent
    sim = build_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, precision=rl.imagined.sim_precision,
                          flow_cfg=cfg.flow, frame_size=cfg.data.image_size, sample_steps=cfg.flow.sample_steps,
                          num_context=cfg.data.context_frames // tf, num_future=cfg.data.predict_frames // tf,
                          action_dim=cfg.model.action_dim, proprio_dim=rl.proprio_dim,
                          execute_latents=rl.imagined_actions_per_decision // tf,
                          proprio_reckoning=reckoning, light_decoder=light_decoder)
    reward_model = as_reward_model(*detector)

    # each process encodes only its rows of the start states, with a copy of the VAE on one of its own devices
    encoder_state = (jax.device_put(jax.device_get(vae_state), jax.local_devices()[0]) if jax.process_count() > 1
                     else vae_state)

    def encode(first_frames, history):  # the real history before a start frame -> the world model's latents
        return encode_history(vae_graphdef, encoder_state, first_frames, history,
                              num_context=cfg.data.context_frames // tf)

    def encode_from_start(prefix, latent_index):  # rl.imagined.start_encoding=prefix: the episode from frame 0
        return encode_prefix(vae_graphdef, encoder_state, prefix, latent_index,
                             num_context=cfg.data.context_frames // tf)

    # rl.imagined.start_encoding=prefix: windows carry each keyframe's episode from frame 0, one length per run
    prefixed = rl.imagined.start_encoding == "prefix"
    prefix_latents = (rl_data.prefix_latents_for(episodes, max_fraction=rl.imagined.keyframe_fraction)
                      if prefixed and episodes is not None else None)

    # keyframes: a host rng that is a function of (seed, step), so a resumed run draws the same
    def draw(sampler, step, rows, **kwargs):
        return sampler(episodes, rl.imagined_starts_per_step, stream_rng(cfg.seed, "grpo/keyframes", step),
                       max_fraction=rl.imagined.keyframe_fraction, min_fraction=rl.imagined.keyframe_from,
                       rows=rows, **kwargs)

    def windows(step, rows=None):
        return draw(rl_data.keyframe_starts, step, rows, prefix_latents=prefix_latents)

    def starts(key, step, rows=None):
        del key
        return start_state(windows(step, rows), encode, rl, encode_prefix=encode_from_start)

    def env_starts(step, rows=None):  # the same keyframes' recorded [time, qpos, qvel], no windows cut
        ep, t = draw(rl_data.keyframe_indices, step, rows)
        return np.asarray(episodes.states[ep, t], np.float32)

    def start_steps(step, rows=None):  # the same keyframes' steps in their episodes
        return np.asarray(draw(rl_data.keyframe_indices, step, rows)[1], np.int32)

    recorded = episodes is not None and episodes.states is not None  # keyframes the real environment can reset to
    return Setup(sim, reward_model, starts, None, encode, env_starts if recorded else None,
                 start_steps if recorded else None, windows, encode_from_start if prefixed else None)


def start_state(pick: dict[str, Any], encode: Callable[..., Any], rl: Any, *,
                encode_prefix: Callable[..., Any] | None = None) -> StartState:
    """Imagined-rollout start states from :func:`~sword_jax.rl.data.keyframe_window`-laid-out picks: their latents
    by ``encode(first_frames, history)``, or, where the picks carry a ``prefix`` and ``encode_prefix`` is given, by
    ``encode_prefix(prefix, latent_index)`` (``rl.imagined.start_encoding=prefix``)."""
    unit = lambda x: jnp.asarray(x, jnp.float32) / jnp.float32(255.0)  # noqa: E731
    if "prefix" in pick and encode_prefix is not None:
        latents = encode_prefix(unit(pick["prefix"]), jnp.asarray(pick["latent_index"], jnp.int32))
    else:
        latents = encode(unit(pick["first_frame"]), unit(pick["history"]))
    return StartState(unit(pick["frame"]), jnp.asarray(pick["proprio"][:, : rl.proprio_dim], jnp.float32),
                      jnp.asarray(tokenize_instructions(pick["instructions"], rl.policy.max_instruction_bytes)),
                      (latents, jnp.asarray(pick["actions"], jnp.float32)))


def skipped_note(point: dict) -> str:
    """A progress line's note of a step that applied no update (``rl.grpo.min_mixed_groups``), else nothing."""
    return "(no update: too few mixed groups) " if point.get("skipped_update") else ""


def payment_note(point: dict, last: int) -> str:
    """A learned-simulator step's progress note of what its trajectories were paid: the imagined success, or
    with a reward paid by execution the real success beside the detector's verdict, and with the closed-loop
    record its frame error and greedy action gap at decision 1 and at decision ``last``, and where the record has
    them the same two of the VAE's round trip of the real frame at decision 1 (the floor a world model with faithful
    dynamics would show: :func:`~sword_jax.rl.imagined_check.closed_loop_fidelity`)."""
    paid = (f"real success of the imagined actions {point['success_rate']:.3f} (the detector said "
            f"{point['detector_success']:.3f}, agreeing on {point['detector_agreement']:.2f})"
            if "detector_success" in point else f"imagined success {point['success_rate']:.3f}")
    if f"closed_loop_action_gap_{last}" in point:  # where the closed loop left the real one: decision 1, last
        paid += (f"; closed loop frame error {point['closed_loop_frame_error_1']:.3f} -> "
                 f"{point[f'closed_loop_frame_error_{last}']:.3f}, greedy action gap "
                 f"{point['closed_loop_action_gap_1']:.3f} -> {point[f'closed_loop_action_gap_{last}']:.3f}")
        if "closed_loop_action_gap_vae_1" in point:
            paid += (f" (the VAE alone at decision 1: frame error {point['closed_loop_frame_error_vae_1']:.3f}, "
                     f"gap {point['closed_loop_action_gap_vae_1']:.3f})")
    return paid


def sampled_mixed(point: dict, rl: Any) -> str:
    """A progress line's note of the step's mixed share among all the groups it sampled, with
    ``rl.imagined.oversample > 1`` (its ``kept_fraction`` is then the updated groups'); empty otherwise."""
    if rl.imagined.oversample == 1:
        return ""
    return f" (mixed {point['sampled_mixed_fraction']:.2f} of {rl.imagined.oversample}x sampled)"


def extra_point(step: int, what: str, result: dict, *, log: Callable[[str], Any] = log, **tags) -> dict:
    """An evaluation stored beside the greedy true-proprio success: logged, and its rates kept with ``tags``."""
    log(f"eval step {step}, {what}: success {result['mean']:.3f} [{result['ci95'][0]:.3f}, {result['ci95'][1]:.3f}]")
    return dict(**tags, **{k: result[k] for k in ("mean", "ci95", "per_task", "episodes", "successes", "outcomes")
                           if k in result})


def mode_point(graphdef, params, rl, step: int, proprio: str, reckoning=None, *, log: Callable[[str], Any] = log,
               **eval_kwargs) -> dict:
    """The real-environment evaluation with the policy reading proprio as ``proprio`` (an input mode of
    the learned simulator), as the extra point stored beside the true-proprio success."""
    other = evaluate_in_sim(graphdef, params, rl, proprio=proprio, reckoning=reckoning, **eval_kwargs)
    return extra_point(step, f"proprio {proprio}", other, proprio=proprio, log=log)


def sampled_point(graphdef, params, rl, step: int, root, *, log: Callable[[str], Any] = log, **eval_kwargs) -> dict:
    """The real-environment evaluation of the sampled policy (``rl.grpo.eval_sampled``: at
    ``rl.grpo.temperature``, the policy GRPO trains), stored as ``sampled`` beside the greedy success.
    Every evaluation of a run draws the same sampling noise (step 0's key, a function of ``root``): common random
    numbers, so the gain between two evaluations pairs each episode's outcomes under the same noise
    (:func:`~sword_jax.rl.env_rollout.gain_interval`)."""
    key = jax.random.fold_in(stream_key(root, "grpo/eval_sampled"), 0)
    other = evaluate_in_sim(graphdef, params, rl, greedy=False, key=key, **eval_kwargs)
    return extra_point(step, f"sampled at temperature {rl.grpo.temperature:g}", other,
                       temperature=rl.grpo.temperature, log=log)


def training_success(history: Sequence[dict], window: int = 10) -> dict:
    """The success of GRPO's own training rollouts (imagined in a world model, real in the env) over its
    first and last ``window`` steps: ``{"metric", "first", "last", "steps"}``, ``{}`` without any."""
    metric = next((k for k in ("success_rate", "rollout_success") if history and k in history[0]), None)
    if metric is None:
        return {}
    values = [float(p[metric]) for p in history if metric in p]
    return {"metric": metric, "first": sum(values[:window]) / len(values[:window]),
            "last": sum(values[-window:]) / len(values[-window:]), "steps": len(values), "window": window}


class Replayer:
    """Replays traced real evaluation episodes in the learned simulator (``rl.imagined.eval_replay_episodes``;
    :mod:`sword_jax.rl.sim_agreement`), with one compile for the run. ``encode_prefix``: the setup's, which
    ``rl.imagined.start_encoding=prefix`` needs (the replays' starts encoded from frame 0)."""

    def __init__(self, cfg, rl, sim, reward_model, encode, root, *, encode_prefix=None):
        self.cfg, self.rl, self.sim, self.reward_model, self.encode = cfg, rl, sim, reward_model, encode
        self.encode_prefix = rl_data.prefix_encoder(rl.imagined.start_encoding, encode_prefix,
                                                    "the replay of real episodes (rl.imagined.eval_replay_episodes)")
        self.key = stream_key(root, "grpo/replay")
        self.tf = cfg.vae.temporal_factor
        self.k = cfg.data.context_frames // self.tf
        self.fn = jax.jit(lambda s, r, st, a, n, key: sim_agreement.replay_actions(
            s, r, st, a, n, success_threshold=rl.success_threshold, key=key,
            settle_steps=rl.imagined.eval_replay_settle_steps, success_frames=rl.imagined.success_frames))

    def trace(self) -> sim_agreement.EpisodeTrace:
        return sim_agreement.EpisodeTrace(self.tf * self.k)

    def report(self, step: int, trace: sim_agreement.EpisodeTrace) -> dict:
        rl, traced = self.rl, trace.result()
        picked = sim_agreement.spread(len(traced.lengths), rl.imagined.eval_replay_episodes)
        traced = sim_agreement.select(traced, picked)
        out = sim_agreement.replay_report(
            traced, self.sim, self.reward_model, self.encode, success_threshold=rl.success_threshold,
            key=jax.random.fold_in(self.key, step), batch=rl.grpo.rollout_batch * rl.grpo.group_size,
            num_context=self.k, frames_per_latent=self.tf, proprio_dim=rl.proprio_dim,
            max_instruction_bytes=rl.policy.max_instruction_bytes, max_steps=self.cfg.sim.max_steps,
            settle_steps=rl.imagined.eval_replay_settle_steps, replay_fn=self.fn, encode_prefix=self.encode_prefix)

        def rate(name):
            r = out[name]
            if r["rate"] is None:
                return "n/a"
            return f"{r['rate']:.3f} [{r['ci95'][0]:.3f}, {r['ci95'][1]:.3f}] of {r['of']}"

        if out["episodes"]:
            log(f"eval step {step}, {out['episodes']} real episodes replayed in the learned simulator: imagined "
                f"success {out['imagined_success']:.3f} vs real {out['real_success']:.3f}; false success "
                f"{rate('false_success')}; missed success {rate('missed_success')}; another noise draw ends "
                f"differently {rate('resample_disagreement')}")
            sweep = out["sustained_success_sweep"]

            def short(r):
                return "n/a" if r["rate"] is None else f"{r['rate']:.3f}"

            log(f"eval step {step}, replay false / missed success if success needed k consecutive frames: " + ", ".join(
                f"k={k}: {short(v['false_success'])} / {short(v['missed_success'])}" for k, v in sweep.items()))
            log(f"eval step {step}, replay imagined success by action h, real successes / real failures: " + ", ".join(
                f"h={h}: {short(v['real_success'])} / {short(v['real_failure'])}"
                for h, v in out["imagined_success_by_horizon"].items()))
        return out


class GRPOStep(NamedTuple):
    """A GRPO run's step as :func:`~sword_jax.rl.grpo_loop.train_grpo` takes it: step ``i`` is
    ``state, metrics = step(state, place(batch_at(i)), key)`` from ``state``. ``sim`` and ``reward_model`` are
    the setup's, placed on ``mesh`` (the batch carries them)."""

    step: Callable[..., Any]
    state: grpo.GRPOState
    batch_at: Callable[[int], Any]
    place: Callable[[Any], Any]
    key: jax.Array
    sim: Any
    reward_model: Any
    mesh: Any

    @property
    def frames_per_chunk(self) -> int:
        """Frames the simulator draws per imagined chunk: the executed actions' (``rl.imagined.execute_steps``),
        not the whole chunk's; what ``step_times.jsonl`` counts per trajectory and rolled chunk."""
        return self.sim.frames_per_step


def grpo_step(cfg, rl, graphdef, params, setup: Setup, *, max_traces: int, env: Any = None,
              workdir: str | None = None) -> GRPOStep:
    """The compiled GRPO step of a run in ``setup``'s simulator from policy ``params``, its initial state and its
    batches (:func:`run_in_learned_simulator`; ``benchmarks.bench_grpo_step`` times it).

    The step runs on the config's mesh, where the world model already lives; the policy state and the other
    weights are placed there once, so the step's inputs and outputs agree and nothing is copied per step. In a
    job of several processes each process makes only its rows of a step's start states (``place`` assembles the
    global batch). The keys are named streams of the root ``cfg.seed``: the start states' folded with the step,
    the update's folding in ``state.step`` itself.

    With ``rl.imagined.reward=executed`` each batch also carries the start states' recorded simulator states
    (``setup.env_starts``) and ``env`` is the real environment they reset (one process only); so does
    ``calibrated``, whose step reads the run's history in ``workdir`` when resumed after its steps paid by
    execution (:func:`~sword_jax.rl.grpo.make_calibrated_step`)."""
    executed = rl.imagined.executes
    if executed and (env is None or setup.env_starts is None):
        raise ValueError(f"rl.imagined.reward={rl.imagined.reward} needs the real environment and start states with "
                         "recorded simulator states (demonstrations whose HDF5 holds 'states')")
    if executed and jax.process_count() > 1:
        raise ValueError(f"rl.imagined.reward={rl.imagined.reward} runs in one process")
    mesh = shd.make_mesh(cfg.mesh)
    sim, reward_model = shd.place((setup.sim, setup.reward_model), shd.shardings_on((setup.sim, setup.reward_model),
                                                                                   mesh))
    state = jax.device_put(grpo.init_state(params, rl), shd.replicated(mesh))
    if rl.imagined.reward == "calibrated":  # paid by execution, then by the detector at the threshold that set
        step_fn = grpo.make_calibrated_step(graphdef, rl, env=env, max_traces=max_traces, mesh=mesh,
                                            rules=cfg.mesh.rules,
                                            history=lambda: read_history(workdir) if workdir else ())
    else:
        step_fn = grpo.make_grpo_step(graphdef, rl, max_traces=max_traces, mesh=mesh, rules=cfg.mesh.rules, env=env)
    root = jax.random.key(cfg.seed)
    starts, starts_key = setup.starts, stream_key(root, "grpo/starts")
    if jax.process_count() > 1:  # each process makes its rows of the global batch of start states
        start_sharding = shd.batch_sharding(mesh, 1, cfg.mesh.rules)
        count = rl.imagined_starts_per_step  # rl.grpo.rollout_batch x rl.imagined.oversample
        shd.check_batch_divides(start_sharding, count, "rl.grpo.rollout_batch" + (
            " x rl.imagined.oversample" if rl.imagined.oversample > 1 else ""))
        rows = shd.rows_held(start_sharding, count)

        def batch_at(step):
            return sim, reward_model, starts(jax.random.fold_in(starts_key, step), step, rows)

        def place(batch):
            batch_sim, batch_reward_model, held = batch
            leaves, treedef = jax.tree.flatten(jax.device_get(held))
            named = {str(i): np.asarray(leaf) for i, leaf in enumerate(leaves)}
            placed = shd.to_global(named, {name: shd.batch_sharding(mesh, value.ndim, cfg.mesh.rules)
                                           for name, value in named.items()}, rows, count)
            return batch_sim, batch_reward_model, jax.tree.unflatten(treedef, [placed[str(i)] for i in range(len(leaves))])
    else:
        def place(batch):  # start states made elsewhere (the VAE's latents, replicated) move onto the batch's sharding
            batch_sim, batch_reward_model, *held = batch
            return (batch_sim, batch_reward_model,
                    *jax.device_put(held, shd.leading_axis_shardings(held, mesh, cfg.mesh.rules)))

        def batch_at(step):
            start = starts(jax.random.fold_in(starts_key, step), step)
            steps = (setup.start_steps(step),) if executed and setup.start_steps is not None else ()
            return (sim, reward_model, start) + ((setup.env_starts(step), *steps) if executed else ())

    return GRPOStep(step_fn, state, batch_at, place, stream_key(root, "grpo/update"), sim, reward_model, mesh)


def run_in_learned_simulator(cfg, rl, graphdef, params, workdir: str, setup: Setup, *, simulator: str,
                             env_eval: dict | None, max_traces: int, env: Any = None,
                             evaluate_real: Callable[[int, Any], tuple[dict, dict]] | None = None) -> dict:
    """GRPO in ``setup``'s simulator (``simulator``: ``world_model`` or ``toy``, the run's identity), resuming
    from ``workdir``.

    In a job of several processes (``jax.distributed``, one mesh over all their devices) the run is data
    parallel: a step's start states are one global batch of which each process makes only the rows its
    devices hold (``setup.starts(key, step, rows)``: the toy draws, the keyframe windows cut and encoded),
    and the step runs over the global mesh, so the gradients are averaged over every process's rollouts.
    Evaluations run identically on every process (deterministic, the same replicated params; the
    real-environment one from a host copy of them), so every process takes the same decisions; only
    process 0 logs and writes the curve, the history and the step times. Every process takes part in
    the checkpoints.

    Args:
      env_eval: ``episodes``, ``envs_factory`` and ``max_steps`` of the ground-truth evaluation
        (:func:`sword_jax.rl.policy_success.evaluate_in_sim`; e.g. ``sim.lockstep.lockstep_evaluation``);
        ``None``: greedy imagined rollouts from ``setup.eval_start`` (the toy).
      max_traces: traces of the jitted step before the retrace guard fails.
      env: the real environment that pays imagined actions with ``rl.imagined.reward=executed`` (:func:`grpo_step`).
      evaluate_real: ``evaluate(step, params) -> (point, extra)`` in place of ``env_eval``'s (e.g. on MJX,
        ``sim.grpo_refresh.mjx_evaluation``); replays of real episodes need ``env_eval``'s traces.

    Returns ``{"curve": evaluation points, "workdir", "history": per-step metrics of the whole run}`` (the
    history is also in ``<workdir>/train_history.jsonl``).
    """
    eval_start, encode = setup.eval_start, setup.encode
    several = jax.process_count() > 1
    say = log if jax.process_index() == 0 else (lambda *_args, **_kwargs: None)
    if evaluate_real is not None and rl.imagined.eval_replay_episodes:
        raise ValueError("rl.imagined.eval_replay_episodes replays the C engine's evaluation episodes; with this "
                         "evaluation pass --rl.imagined.eval_replay_episodes=0")
    run = grpo_step(cfg, rl, graphdef, params, setup, max_traces=max_traces, env=env, workdir=workdir)
    sim, reward_model, mesh = run.sim, run.reward_model, run.mesh
    root = jax.random.key(cfg.seed)
    if eval_start is not None:
        greedy = jax.jit(lambda p: imagined_rollout(graphdef, p, sim, reward_model, eval_start, rl,
                                                    key=stream_key(root, "grpo/toy_eval"), greedy=True).success,
                         **({"out_shardings": shd.replicated(mesh)} if several else {}))

    act = make_act_fns(graphdef, rl)  # one compile for every evaluation of the run
    replay = (Replayer(cfg, rl, sim, reward_model, encode, root, encode_prefix=setup.encode_prefix)
              if encode and rl.imagined.eval_replay_episodes else None)

    def evaluate(step, params):
        extra = {}
        if evaluate_real is not None:
            return evaluate_real(step, params)
        if env_eval is None:
            success = np.asarray(greedy(params))
            result = {"per_task": {"toy": float(success.mean())}, "mean": float(success.mean()),
                      "episodes": int(success.size), "where": "imagined (toy)"}
        else:
            if several:  # the C engine's policy calls run on this process's device
                params = jax.device_get(params)
            kwargs = dict(env_eval, act=act)
            trace = replay.trace() if replay else None
            result = evaluate_in_sim(graphdef, params, rl, trace=trace, **kwargs)
            result["where"] = "mujoco"
            if rl.imagined.eval_masked_proprio:
                extra = {"proprio_masked": mode_point(graphdef, params, rl, step, "missing", log=say, **kwargs)}
            if rl.grpo.eval_sampled:
                extra["sampled"] = sampled_point(graphdef, params, rl, step, root, log=say, **kwargs)
            if replay:
                extra["replay"] = replay.report(step, trace)
        say(f"eval step {step}: success {result['mean']:.3f} {json.dumps(result['per_task'])}")
        return result, extra

    def progress(point, eta):
        paid = payment_note(point, rl.imagined.max_chunks - 1)
        return (f"grpo step {point['step']}/{rl.grpo.steps} {paid} "
                f"return {point['mean_return']:.3f} loss {point['loss']:.4f} clip {point['clip_fraction']:.3f} "
                f"kept {point['kept_fraction']:.2f}{sampled_mixed(point, rl)} nll {point['behaviour_nll']:.3f} "
                f"{skipped_note(point)}eta {eta:.0f}s")

    run_id = grpo_run_id(rl, seed=cfg.seed, simulator=simulator, **{"sim.tasks": cfg.sim.tasks})
    result, curve = train_grpo(run.step, run.state, run.batch_at, key=run.key, rl=rl, workdir=workdir,
                               evaluate=evaluate, run_id=run_id, progress=progress, log=say,
                               frames_per_chunk=run.frames_per_chunk, place=run.place)
    return {"curve": curve, "workdir": workdir, "history": result.history}
