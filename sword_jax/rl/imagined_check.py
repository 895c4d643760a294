"""The policy's own imagined rollouts checked in the real environment.

The refresh's replay (:mod:`sword_jax.rl.sim_agreement`) feeds *real* episodes' actions through the learned
simulator: it asks whether the simulator's verdict follows the actions of trajectories the real world made. GRPO
learns from the other direction: trajectories the policy made *inside* the simulator, rewarded by its verdict.
Here those are checked: the policy is rolled out in the simulator from start states the real environment can
also be put in, in groups as GRPO rolls out, and each imagined trajectory's executed actions are then executed
open loop in the real environment from the same start. Whether the real world succeeds with the same actions is
the truth of the reward GRPO was given (VLA-RFT's verified rewards, measured rather than trained on). Its share
of imagined successes that fail in reality rises as a policy learns to exploit the simulator.

The actions are those the simulator executed, decoded from the rollout's tokens (bin centres, as the simulator
received them), each applied once; a trajectory stops where its imagined rollout stopped (its success, or the
horizon). An imagined success is placed at the last action of the decision that reached it (the rollout keeps
one score per decision).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jaxtyping import Array, Bool, Float, Int

from sword_jax.rl import sim_agreement
from sword_jax.rl.policy import resize_frames, tokens_to_actions
from sword_jax.rl.rollout import Rollout, trajectory_returns


class CheckedRollouts(NamedTuple):
    """Imagined trajectories and the real outcome of their actions (``[n]`` / ``[n, T]`` arrays).

    Attributes:
      imagined_first: ``[n]`` action index of each imagined success (the last action of its decision), -1 if none.
      real_first: ``[n]`` action index after which the real environment first reached success with the same
        actions (within the imagined trajectory's actions), -1 if never.
      scores: ``[n, T]`` the detector's score of each decision's last frame, repeated over the decision's actions
        (0 after the imagined trajectory ended).
      lengths: ``[n]`` actions each imagined trajectory executed.
    """

    imagined_first: np.ndarray
    real_first: np.ndarray
    scores: np.ndarray
    lengths: np.ndarray


def executed_actions(rollout: Rollout, action_bins: int) -> tuple[Float[Array, "n t a"], Int[Array, " n"]]:
    """``(actions [N, C * E, A], lengths [N])``: the actions the simulator executed (``E`` per decision),
    decision after decision, and how many of them each trajectory took before it ended."""
    actions = tokens_to_actions(rollout.tokens, action_bins)  # [N, C, E, A]
    n, c, e, a = actions.shape
    lengths = (jnp.sum(rollout.valid, axis=1) * e).astype(jnp.int32)
    return actions.reshape(n, c * e, a), lengths


def imagined_first_success(rollout: Rollout) -> Int[Array, " n"]:
    """``[N]`` the last action index of the decision at which each imagined trajectory succeeded, -1 if none."""
    e = rollout.tokens.shape[2]
    taken = jnp.sum(rollout.valid, axis=1).astype(jnp.int32)
    return jnp.where(rollout.success, taken * e - 1, -1)


def _open_loop_step(env: Any, actions: Float[Array, "n t a"], lengths: Int[Array, " n"]) -> Any:
    """The scan body of an open-loop execution: ``((state, first), i) -> ((state, first), obs)``."""
    def body(carry, i):
        state, first = carry
        state, obs, success = env.step(state, actions[:, i])
        first = jnp.where((first < 0) & success & (i < lengths), i, first)
        return (state, first), obs
    return body


def execute_open_loop(env: Any, starts: Any, actions: Float[Array, "n t a"], lengths: Int[Array, " n"]
                      ) -> Int[Array, " n"]:
    """Runs fixed action sequences in a pure JAX environment (``reset(starts) -> (state, obs)``,
    ``step(state, actions [n, A]) -> (state, obs, success [n])``) from ``starts``; returns for each the index
    of the first action after which it succeeded, among its first ``lengths`` actions, -1 if none."""
    state, _ = env.reset(starts)
    n, t = actions.shape[:2]
    body = _open_loop_step(env, actions, lengths)
    (_, first), _ = jax.lax.scan(lambda carry, i: (body(carry, i)[0], None), (state, jnp.full((n,), -1, jnp.int32)),
                                 jnp.arange(t))
    return first


def execute_observed(env: Any, starts: Any, actions: Float[Array, "n t a"], lengths: Int[Array, " n"], *,
                     every: int, rows: int) -> tuple[Int[Array, " n"], Any]:
    """:func:`execute_open_loop`, also keeping the real frame (``obs["frames"]``) reached after every ``every``-th
    action by the first ``rows`` sequences: ``(first [n], frames [rows, t // every, H, W, 3])``, frame ``k`` the
    one after decision ``k``'s actions (``every`` actions a decision)."""
    n, t = actions.shape[:2]
    if every < 1 or t % every or not 1 <= rows <= n:
        raise ValueError(f"execute_observed: every={every} must divide the {t} actions and rows={rows} be in 1..{n}")
    state, _ = env.reset(starts)
    body = _open_loop_step(env, actions, lengths)

    def decision(carry, d):
        carry, obs = jax.lax.scan(body, carry, d * every + jnp.arange(every))
        return carry, obs["frames"][-1, :rows]

    (_, first), frames = jax.lax.scan(decision, (state, jnp.full((n,), -1, jnp.int32)), jnp.arange(t // every))
    return first, jnp.swapaxes(frames, 0, 1)


def greedy_actions(policy: Any, frames: Float[Array, "n s s 3"], instruction_tokens: Int[Array, "n l"],
                   proprio: Float[Array, "n p"], proprio_valid: Float[Array, " n"], *, executed: int,
                   action_bins: int) -> Float[Array, "n ea"]:
    """``[n, executed x A]`` the policy's greedy actions (bin centres of the argmax tokens) of the first ``executed``
    entries of its chunk, flat, on ``frames`` at its own size in [0, 1]. ``policy(frames, tokens, proprio,
    proprio_valid)`` gives the logits ``[n, T, A, bins]`` (a merged :class:`~sword_jax.rl.policy.VLAPolicy`). The
    mean absolute difference of two of these rows is the action gap of :func:`closed_loop_fidelity`."""
    logits = policy(frames, instruction_tokens, proprio, proprio_valid)[:, :executed]
    return tokens_to_actions(jnp.argmax(logits, axis=-1), action_bins).reshape(frames.shape[0], -1)


def high_frequency_energy(frames: Float[Array, "... s s 3"]) -> Float[Array, "..."]:
    """Per frame (in [0, 1]) the mean squared 4-neighbour Laplacian of its grey image, over the interior pixels:
    the energy of its finest detail (edges, texture). A blur lowers it, a sharp frame of the same scene keeps it;
    the ratio of two frames' is the sharpness of :func:`closed_loop_fidelity`."""
    grey = jnp.mean(frames.astype(jnp.float32), axis=-1)
    laplacian = (4.0 * grey[..., 1:-1, 1:-1] - grey[..., 2:, 1:-1] - grey[..., :-2, 1:-1] - grey[..., 1:-1, 2:]
                 - grey[..., 1:-1, :-2])
    return jnp.mean(jnp.square(laplacian), axis=(-2, -1))


def sharpness_ratio(frames: Float[Array, "... s s 3"], reference: Float[Array, "... s s 3"]) -> Float[Array, "..."]:
    """:func:`high_frequency_energy` of ``frames`` over that of ``reference``, frame by frame: 1 for frames as
    sharp as the reference, below 1 for blurred ones (the mean of several futures, a ghost of two poses), above 1
    for noisier ones; two flat frames count as equally sharp."""
    tiny = jnp.float32(1e-8)
    return (high_frequency_energy(frames) + tiny) / (high_frequency_energy(reference) + tiny)


def closed_loop_fidelity(graphdef: Any, params: Any, rollout: Rollout, real_frames: Any, *, image_size: int,
                         action_bins: int, round_trip: Callable[[Array], Array] | None = None,
                         read_state: Callable[[Array], Array] | None = None, gripper_closed_below: float = 0.04
                         ) -> dict[str, Float[Array, ""]]:
    """Where the closed loop through the simulator leaves the real one, decision by decision.

    ``real_frames [m, C, H, W, 3]`` (:func:`execute_observed`) are the real frames the first ``m`` trajectories'
    own actions reached by the end of each decision. At decision ``k >= 1`` the policy read the simulator's frame
    (``rollout.obs_frames[:, k]``); the real world, given the same actions, shows ``real_frames[:, k - 1]``. Per
    decision, over the trajectories that took it: ``closed_loop_frame_error_k``, the mean absolute difference of
    the two frames at the policy's size (in [0, 1]); ``closed_loop_action_gap_k``, the mean absolute difference
    of the policy's greedy actions on the two (action units, over the executed actions of the chunk). Decision 0
    reads the real start frame in both, so it is left out. A simulator equal to the environment gives 0 at every
    decision; a gap that appears at decision 1 says the policy misreads the simulator's frames, one that grows
    with ``k`` says the simulator drifts from where the actions lead.

    Three more per decision place the error: ``closed_loop_frame_error_prev_k`` and ``closed_loop_action_gap_prev_k``,
    the simulator's frame (and the greedy actions on it) against the real frame one decision earlier (the start
    frame for ``k = 1``), and ``closed_loop_motion_k``, how far the real frame moved over the decision (the same
    two real frames). A simulator that shows the scene before the actions moved it (a lag of a decision, or a
    scene that does not move) has the ``_prev`` figures near 0 and ``frame_error`` near ``motion``; its image
    errors (a blur, a colour shift) move the frame error far more than the greedy actions.
    ``closed_loop_sharpness_k`` tells a blur apart: the simulator's frame's finest detail over the real frame's
    (:func:`sharpness_ratio`, at the policy's size); a world model that predicts the mean of the futures it cannot
    tell apart (a smeared arm, a ghost of two poses) scores well below 1 while its frame error stays small.

    ``round_trip`` (frames ``[n, H, W, 3]`` in [0, 1] at the real frames' size -> the frames the simulator's
    decoder shows of them, at its frame size: :meth:`~sword_jax.rl.learned_simulator.LearnedSimulator.round_trip`,
    the world model's VAE round trip) splits each decision's error into the decoder's share and the dynamics'.
    It runs on the real frames at their own resolution, before the resize to the policy's size (the simulator
    decodes at its frame size, the rollout resizes afterwards), and adds per decision
    ``closed_loop_frame_error_vae_k``, the round-tripped real frame against the real frame (at the policy's size),
    ``closed_loop_action_gap_vae_k``, the greedy actions on the two, and ``closed_loop_sharpness_vae_k``, the
    round-tripped frame's sharpness against the real one's: the floor a world model that predicted
    the real scene's latents exactly would still show through this decoder. ``frame_error`` near
    ``frame_error_vae`` and ``action_gap`` near ``action_gap_vae`` say the world model's dynamics are faithful and
    the VAE is what the policy misreads; the excess over them is the dynamics'. A world model decoding with the
    light decoder has no round trip (its weights hold no VAE encoder): its runs log no ``_vae`` figures.

    ``read_state`` (frames ``[n, H, W, 3]`` in [0, 1], any size -> ``[n, 7]`` end effector xyz, gripper opening,
    bowl xyz in metres: the state probe of :mod:`sword_jax.evaluation.probe`) says which part of the scene has left:
    per decision ``closed_loop_ee_cm`` and ``closed_loop_bowl_cm``, the distance between what it reads on the
    simulator's frame and on the real frame, ``closed_loop_gripper_agree`` whether both read the gripper closed
    (opening below ``gripper_closed_below``) or both open, and ``closed_loop_ee_motion_cm`` /
    ``closed_loop_bowl_motion_cm``, how far the readout moved on the real frames over the decision. An arm that goes
    where the actions send it has ``ee_cm`` near 0 whatever the bowl does; the readouts share the probe's own error
    on real frames (its floor, recorded where the probe was trained). With ``round_trip`` too, the same three on the
    round-tripped real frames against the real ones, ``closed_loop_ee_cm_vae``, ``closed_loop_bowl_cm_vae`` and
    ``closed_loop_gripper_agree_vae``: what the readouts show of a world model that predicted the real scene's
    latents exactly (the probe's error on decoded frames plus the decoder's), the floor its ``ee_cm`` and
    ``bowl_cm`` are read against."""
    m, c = real_frames.shape[:2]
    if rollout.obs_frames.shape[1] != c or m > rollout.obs_frames.shape[0]:
        raise ValueError(f"closed_loop_fidelity: real frames {real_frames.shape[:2]} do not match the rollout's "
                         f"{rollout.obs_frames.shape[:2]} decisions")
    out: dict[str, Float[Array, ""]] = {}
    if c < 2:
        return out
    policy = nnx.merge(graphdef, params)
    e = rollout.tokens.shape[2]
    imagined = resize_frames(rollout.obs_frames[:m, 1:], image_size)
    real = resize_frames(real_frames[:, :-1], image_size)
    taken = rollout.valid[:m, 1:].astype(jnp.float32)
    flat = lambda x: x.reshape((m * (c - 1),) + x.shape[2:])  # noqa: E731 - (m, C - 1, ...) -> (m (C - 1), ...)
    tokens = jnp.repeat(rollout.instruction_tokens[:m], c - 1, axis=0)
    proprio, valid = flat(rollout.proprio[:m, 1:]), flat(rollout.proprio_valid[:m, 1:])

    def greedy(frames):
        return greedy_actions(policy, flat(frames), tokens, proprio, valid, executed=e, action_bins=action_bins)

    # the real frame a decision earlier: the start frame (read by both at decision 0), then the real ones
    real_prev = jnp.concatenate([resize_frames(rollout.obs_frames[:m, :1], image_size), real[:, :-1]], axis=1)
    error = lambda a, b: jnp.mean(jnp.abs(a - b), axis=(2, 3, 4))  # noqa: E731 - (m, C - 1, s, s, 3) -> (m, C - 1)
    gap = lambda a, b: jnp.mean(jnp.abs(a - b), axis=-1).reshape(m, c - 1)  # noqa: E731 - greedy actions' gap
    on_imagined, on_real = greedy(imagined), greedy(real)
    figures = {"frame_error": error(imagined, real), "action_gap": gap(on_imagined, on_real),
               "frame_error_prev": error(imagined, real_prev), "action_gap_prev": gap(on_imagined, greedy(real_prev)),
               "motion": error(real, real_prev), "sharpness": sharpness_ratio(imagined, real)}
    # frames as floats in [0, 1] (the environment's may be uint8)
    as_unit = lambda x: (x.astype(jnp.float32) / jnp.float32(255.0) if x.dtype == jnp.uint8  # noqa: E731
                         else x.astype(jnp.float32))
    if round_trip is not None:  # the real frames through the simulator's decoder, at their own size, then resized
        seen = as_unit(real_frames[:, :-1])
        tripped = round_trip(seen.reshape((m * (c - 1),) + seen.shape[2:]))
        tripped = tripped.reshape((m, c - 1) + tripped.shape[1:])  # at the simulator's frame size
        at_policy = resize_frames(tripped, image_size)
        figures.update(frame_error_vae=error(at_policy, real), action_gap_vae=gap(greedy(at_policy), on_real),
                       sharpness_vae=sharpness_ratio(at_policy, real))
    if read_state is not None:  # each frame set read at its own size (the probe resizes): simulator's, real, start
        from sword_jax.evaluation.probe import BOWL, EE, GRIPPER

        def state(frames):
            frames = as_unit(frames)
            n = frames.shape[0] * frames.shape[1]
            return read_state(frames.reshape((n,) + frames.shape[2:])).reshape(frames.shape[:2] + (-1,))

        on_sim, on_env = state(rollout.obs_frames[:m, 1:]), state(real_frames[:, :-1])
        before = jnp.concatenate([state(rollout.obs_frames[:m, :1]), on_env[:, :-1]], axis=1)
        cm = lambda a, b: jnp.float32(100.0) * jnp.linalg.norm(a - b, axis=-1)  # noqa: E731 - metres -> cm
        closed = lambda x: x[..., GRIPPER] < jnp.float32(gripper_closed_below)  # noqa: E731
        figures.update(ee_cm=cm(on_sim[..., EE], on_env[..., EE]), bowl_cm=cm(on_sim[..., BOWL], on_env[..., BOWL]),
                       gripper_agree=(closed(on_sim) == closed(on_env)).astype(jnp.float32),
                       ee_motion_cm=cm(on_env[..., EE], before[..., EE]),
                       bowl_motion_cm=cm(on_env[..., BOWL], before[..., BOWL]))
        if round_trip is not None:  # the probe on the decoder's view of the real frames: the readouts' floor
            on_tripped = state(tripped)
            figures.update(ee_cm_vae=cm(on_tripped[..., EE], on_env[..., EE]),
                           bowl_cm_vae=cm(on_tripped[..., BOWL], on_env[..., BOWL]),
                           gripper_agree_vae=(closed(on_tripped) == closed(on_env)).astype(jnp.float32))
    count = jnp.maximum(jnp.sum(taken, axis=0), 1.0)
    for name, per_trajectory in figures.items():
        per_decision = jnp.sum(per_trajectory * taken, axis=0) / count
        for k in range(1, c):
            out[f"closed_loop_{name}_{k}"] = per_decision[k - 1]
    return out


def decision_scores(rollout: Rollout) -> Float[Array, "n t"]:
    """``[N, C * E]`` each decision's score (of its last frame) over its ``E`` actions, 0 where it was not taken."""
    e = rollout.tokens.shape[2]
    return jnp.repeat(rollout.scores * rollout.valid, e, axis=1)


def check(rollout: Rollout, env: Any, env_starts: Any, action_bins: int) -> CheckedRollouts:
    """Executes ``rollout``'s trajectories in ``env`` from ``env_starts`` (one per trajectory, the states the
    imagined ones started from); jit-able, device arrays (``jax.device_get`` gives the host's)."""
    actions, lengths = executed_actions(rollout, action_bins)
    return CheckedRollouts(imagined_first=imagined_first_success(rollout),
                           real_first=execute_open_loop(env, env_starts, actions, lengths),
                           scores=decision_scores(rollout), lengths=lengths)


def paid_by_execution(rollout: Rollout, real_first: Int[Array, " n"], cfg: Any) -> Rollout:
    """``rollout`` as the real environment pays it (``rl.imagined.reward=executed``): a trajectory succeeds
    where its executed actions reached success in reality (``real_first``, the action index, -1 if never);
    its decisions after the one holding that action are masked, the success is its reward (at that decision),
    and its return follows ``rl.imagined.return_rule`` as an imagined one's does. Frames, tokens and the
    detector's scores are kept (the scores are what the detector said, paid for nothing)."""
    e = rollout.tokens.shape[2]
    c = rollout.valid.shape[1]
    success = real_first >= 0
    last = jnp.where(success, real_first // e, c - 1)  # the decision that holds the real success
    chunks = jnp.arange(c)[None, :]
    valid = rollout.valid * (chunks <= last[:, None]).astype(rollout.valid.dtype)
    rewards = ((chunks == last[:, None]) & success[:, None]).astype(jnp.float32)
    return rollout._replace(valid=valid, rewards=rewards, success=success,
                            returns=trajectory_returns(rewards, success, cfg))


# the metrics of a step paid by execution that are NaN by definition where an outcome is missing (no real failure,
# no real success, nothing paid at the bound): not a sign of a non-finite update (grpo_loop.grpo_metrics_finite)
UNDEFINED_AS_NAN = ("detector_false_success", "detector_auc", "detector_threshold_bounded", "detector_recall_bounded",
                    "detector_precision_bounded")


def detector_metrics(said: Bool[Array, " n"], real: Bool[Array, " n"]) -> dict[str, Float[Array, ""]]:
    """The detector's verdict on trajectories the real environment paid (``rl.imagined.reward=executed``).

    ``said`` is the success the detector would have paid each trajectory, by the rule the detector's reward uses
    (:func:`~sword_jax.rl.rollout.imagined_rollout` with ``stop_on_success=False``: a run of
    ``rl.imagined.success_frames`` frames at or above the threshold, any frame of any chunk); ``real`` the real
    outcome. Returns ``detector_success``, ``detector_agreement`` with the real outcome, and
    ``detector_false_success``: the real failures it would have paid (NaN with none), the rate GRPO in the
    detector's reward is exposed to at this step."""
    said, real = jnp.asarray(said, bool), jnp.asarray(real, bool)
    failures = jnp.sum((~real).astype(jnp.float32))
    return {"detector_success": jnp.mean(said.astype(jnp.float32)),
            "detector_agreement": jnp.mean((said == real).astype(jnp.float32)),
            "detector_false_success": jnp.sum((said & ~real).astype(jnp.float32)) / jnp.where(failures > 0, failures,
                                                                                             jnp.nan)}


# where a start stands in its episode, by the actions already taken there (its keyframe's step): the lower edges of
# the bins :func:`outcomes_by_start` counts executed trajectories in (the last bin open above)
START_STEP_EDGES = (0, 24, 48, 72, 96)


def outcomes_by_start(start_steps: Int[Array, " n"], said: Bool[Array, " n"] | None, real: Bool[Array, " n"],
                      edges: tuple[int, ...] = START_STEP_EDGES) -> dict[str, Float[Array, ""]]:
    """Trajectories counted by where their start stands in its episode: the world model's executed ones
    (``rl.imagined.reward=executed``), or ground truth's (``said`` None: no detector, no ``_said`` counts).

    ``start_steps`` is each trajectory's start step (its keyframe's index in the demonstration: the actions
    already taken there), ``said`` the detector's verdict on its imagined frames, ``real`` its real outcome. For
    each bin ``[edges[i], edges[i + 1])`` (the last open above), named by its lower edge ``a``: ``start_a<a>_rollouts``
    (the trajectories from there), ``start_a<a>_real`` (their real successes), ``start_a<a>_said`` (the
    detector's verdicts of success) and ``start_a<a>_said_real`` (those verdicts that reality paid too), all
    counts, so that steps pool by summing and an empty bin is 0, not NaN.
    Where in the task the simulator's closed loop keeps reality's payment, and where its frames show successes
    that did not happen."""
    if not edges or edges[0] != 0 or any(b <= a for a, b in zip(edges, edges[1:])):
        raise ValueError(f"outcomes_by_start: edges must start at 0 and rise, got {edges}")
    steps, real = jnp.asarray(start_steps, jnp.int32), jnp.asarray(real, bool)
    index = jnp.sum(steps[:, None] >= jnp.asarray(edges, jnp.int32)[None, :], axis=1) - 1  # -1: before edge 0
    out = {}
    for i, lower in enumerate(edges):
        here = index == i
        out[f"start_a{lower}_rollouts"] = jnp.sum(here.astype(jnp.float32))
        out[f"start_a{lower}_real"] = jnp.sum((here & real).astype(jnp.float32))
        if said is not None:
            verdict = jnp.asarray(said, bool)
            out[f"start_a{lower}_said"] = jnp.sum((here & verdict).astype(jnp.float32))
            out[f"start_a{lower}_said_real"] = jnp.sum((here & verdict & real).astype(jnp.float32))
    return out


def detector_separation(peaks: Float[Array, "n c"], real: Bool[Array, " n"], *, max_false_success: float = 0.05
                        ) -> dict[str, Float[Array, ""]]:
    """How well the detector's scores on trajectories that the real environment paid separate their real outcomes,
    whatever its threshold (``rl.imagined.reward=executed``; read by the rule of ``rl.imagined.success_frames =
    1``: a trajectory is said to succeed where its highest frame score reaches the threshold).

    ``peaks`` are each chunk's highest frame score (:attr:`~sword_jax.rl.rollout.Rollout.peaks`), ``real`` the
    real outcomes. Returns ``detector_auc``, the chance that a real success scores above a real failure (ties
    count half), and, where a trajectory is paid when it scores above ``detector_threshold_bounded`` (the real
    failure's score that leaves at most ``max_false_success`` of the real failures above it), the real successes
    paid (``detector_recall_bounded``) and the share of the paid that are real successes
    (``detector_precision_bounded``). The cut needs real failures alone; the AUC and the recall need both
    outcomes; NaN where what a figure needs is missing, and the precision where nothing is paid.
    What a threshold calibrated on the policy's own closed loop could give GRPO in the detector's reward."""
    if not 0.0 <= max_false_success < 1.0:
        raise ValueError(f"detector_separation: max_false_success must be in [0, 1), got {max_false_success}")
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    top = jnp.max(f32(peaks), axis=1)
    real = jnp.asarray(real, bool)
    wins, losses = jnp.sum(f32(real)), jnp.sum(f32(~real))
    both = (wins > 0) & (losses > 0)
    above = f32(top[:, None] > top[None, :]) + 0.5 * f32(top[:, None] == top[None, :])
    auc = jnp.sum(jnp.where(real[:, None] & ~real[None, :], above, 0.0)) / jnp.maximum(wins * losses, 1.0)
    # the failures' scores from the highest down: at most floor(bound x failures) of them may be paid, so the cut
    # is the next one, and paid means strictly above it (a step above it would vanish where denormals flush to 0)
    failing = jnp.sort(jnp.where(real, -jnp.inf, top))[::-1]
    allowed = jnp.floor(jnp.float32(max_false_success) * losses).astype(jnp.int32)
    cut = failing[jnp.minimum(allowed, top.shape[0] - 1)]
    said = top > cut
    paid = jnp.sum(f32(said & real))
    nan = jnp.float32(jnp.nan)
    return {"detector_auc": jnp.where(both, auc, nan),
            "detector_threshold_bounded": jnp.where(losses > 0, cut, nan),
            "detector_recall_bounded": jnp.where(both, paid / jnp.maximum(wins, 1.0), nan),
            "detector_precision_bounded": jnp.where((losses > 0) & jnp.any(said),
                                                    paid / jnp.maximum(jnp.sum(f32(said)), 1.0), nan)}


def report(checked: CheckedRollouts, group_size: int, horizons: tuple[int, ...] = sim_agreement.HORIZON_SWEEP
           ) -> dict[str, Any]:
    """The imagined verdicts against the real outcomes of the same actions.

    :func:`~sword_jax.rl.sim_agreement.agreement` (``false_success``: real failures GRPO was paid for), plus
    ``precision``: the share of imagined successes that succeed in reality (the share of GRPO's positive rewards
    that are true), and with ``group_size`` > 1 the separation inside the groups
    (:func:`~sword_jax.rl.sim_agreement.within_group_separation`: whether the verdict ranks a group's real
    successes above its real failures, what GRPO's advantages read).
    """
    real = np.asarray(checked.real_first) >= 0
    imagined = np.asarray(checked.imagined_first) >= 0
    out = sim_agreement.agreement(real, imagined)
    counts = out["counts"]
    out["precision"] = sim_agreement.wilson_rate(counts["real_and_imagined"],
                                          counts["real_and_imagined"] + counts["imagined_only"])
    out["mean_actions"] = float(np.mean(checked.lengths)) if real.size else None
    if group_size > 1:
        out["within_group"] = sim_agreement.within_group_separation(
            real, np.asarray(checked.imagined_first), group_size, horizons=horizons, scores=np.asarray(checked.scores))
    return out


def still_window(frames: np.ndarray, proprio: np.ndarray, instructions: list[str], *, num_context: int,
                 frames_per_latent: int, action_dim: int) -> dict[str, Any]:
    """A start at rest laid out as :func:`~sword_jax.rl.data.keyframe_window` lays out a keyframe: its history
    is the first frame held still, its actions zero (a scene the environment has just settled)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.dtype != np.uint8:
        raise ValueError(f"still_window: frames must be [n, H, W, 3] uint8, got {frames.shape} {frames.dtype}")
    n = frames.shape[0]
    if len(instructions) != n or proprio.shape[0] != n:
        raise ValueError(f"still_window: {n} frames need as many proprio rows and instructions, got "
                         f"{proprio.shape[0]} and {len(instructions)}")
    history = np.repeat(frames[:, None], frames_per_latent * (num_context + 1), axis=1)
    return {"frame": frames, "proprio": np.asarray(proprio, np.float32), "first_frame": frames, "history": history,
            "actions": np.zeros((n, 1 + frames_per_latent * num_context, action_dim), np.float32),
            "instructions": list(instructions)}

