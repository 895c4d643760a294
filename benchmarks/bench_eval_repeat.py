"""Is GRPO's MJX evaluation repeatable? The same policy evaluated several times in one process, with the same
starts and keys, as a GRPO run evaluates it at each of its points.

Every gain a GRPO run reports is its last evaluation minus its first, paired episode by episode
(:func:`sword_jax.rl.env_rollout.gain_interval`). With the same policy, starts and sampling noise, an episode's
outcome should then only change where the policy changed. On a GPU it can change anyway: XLA may sum with atomic
adds whose order varies, and a closed loop of up to 220 actions carries a last-bit difference into a different
grasp. This benchmark measures how far: it builds the evaluation of ``benchmarks.bench_policy grpo
--rl.env.backend=mjx`` (:class:`~sword_jax.rl.jax_env_grpo.EnvGRPO`, its greedy, sampled and proprio-masked
policies) and calls :meth:`~sword_jax.rl.jax_env_grpo.EnvGRPO.evaluate` ``--repeats`` times with the same
arguments. Per policy it reports each repeat's success and seconds (the first includes compilation) and, for each
later repeat, the episodes whose outcome differs from the first repeat's (:func:`compare_repeats`).

``--deterministic`` adds ``--xla_gpu_deterministic_ops=true`` to ``XLA_FLAGS`` before JAX starts its backend, to
measure what determinism costs and whether it makes the evaluation repeatable. Config overrides
(``--rl.section.key=value``) apply as in ``bench_policy``; the GRPO recipe's evaluation reads e.g.
``--rl.grpo.temperature=0.5 --rl.env.proprio=missing``::

    python -m benchmarks.bench_eval_repeat --policy runs/p/policy_d50.npz --out runs/eval_repeat \\
        --rl.grpo.temperature=0.5 --rl.env.proprio=missing [--deterministic] [--record]

``eval_repeat.json`` is rewritten after every repeat (``"complete": false`` until the last), with each repeat's
outcomes, so a run cut off mid-way keeps the repeats it finished. ``--record`` writes ``mjx_eval_repeat_small`` (with
``--deterministic``: ``mjx_eval_repeat_deterministic_small``) to ``benchmarks/results/latest.json``: its value is the largest share, over the policies and the later repeats, of
episodes whose outcome differed from the first repeat's. ``--from FILE --record`` records a saved
``eval_repeat.json`` (a GPU run's, on any machine) without evaluating anything; it needs two repeats or more.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence

import numpy as np

from sword_jax import cli
from sword_jax.atomic_write import write_json_atomic
from sword_jax.pipeline.launch import DETERMINISTIC_OPS as DETERMINISTIC_FLAG
from sword_jax.pipeline.launch import with_flag

POLICIES = ("greedy", "sampled", "sampled_proprio_masked")  # EnvGRPO.evaluate's point and extras


def compare_repeats(outcomes: Sequence[np.ndarray]) -> dict:
    """Each repeat's success rate and, for each later repeat, its episodes whose outcome differs from the first
    repeat's: ``{"success": [...], "differing": [...], "differing_share": [...], "gained": [...], "lost": [...]}``
    (``gained``: failed in the first repeat, succeeded in this one)."""
    runs = [np.asarray(o, bool).ravel() for o in outcomes]
    if len(runs) < 2:
        raise ValueError(f"compare_repeats: needs at least 2 repeats, got {len(runs)}")
    if len({r.size for r in runs}) != 1 or runs[0].size == 0:
        raise ValueError(f"compare_repeats: every repeat must hold the same episodes, got sizes {[r.size for r in runs]}")
    first = runs[0]
    gained = [int(np.sum(~first & r)) for r in runs[1:]]
    lost = [int(np.sum(first & ~r)) for r in runs[1:]]
    differing = [g + l for g, l in zip(gained, lost)]
    return {"episodes": int(first.size), "success": [float(r.mean()) for r in runs], "differing": differing,
            "differing_share": [d / first.size for d in differing], "gained": gained, "lost": lost}


def repeat_evaluations(runner, params, repeats: int, *, masked: bool,
                       log=lambda line: print(line, flush=True), on_repeat=None) -> tuple[dict, list[float]]:
    """``repeats`` calls of ``runner.evaluate(params, step=0, ...)`` (an :class:`~sword_jax.rl.jax_env_grpo.EnvGRPO`
    whose probe is started), every one with the same arguments: ``({policy: compare_repeats(...)}, seconds of each
    repeat)``, for the greedy and sampled policies and, with ``masked``, the sampled one reading proprio masked.
    ``on_repeat(outcomes, seconds)``, if given, is called after every repeat with the outcomes so far
    (``{policy: [bool array per repeat]}``)."""
    from sword_jax.rl.env_rollout import point_outcomes

    outcomes: dict[str, list[np.ndarray]] = {p: [] for p in POLICIES}
    seconds = []
    for repeat in range(repeats):
        start = time.perf_counter()
        point, extra = runner.evaluate(params, step=0, sampled=True, masked=masked)
        seconds.append(round(time.perf_counter() - start, 1))
        for policy in POLICIES:
            figures = point if policy == "greedy" else extra.get(policy)
            if figures is not None:
                outcomes[policy].append(point_outcomes(figures))
        log(f"[eval-repeat] repeat {repeat}: greedy {point['mean']:.3f}, sampled {extra['sampled']['mean']:.3f}"
            + (f", proprio masked {extra['sampled_proprio_masked']['mean']:.3f}" if masked else "")
            + f" ({seconds[-1]} s)")
        if on_repeat is not None:
            on_repeat(outcomes, seconds)
    return {p: compare_repeats(o) for p, o in outcomes.items() if o}, seconds


def outcome_strings(outcomes: dict[str, list[np.ndarray]]) -> dict[str, list[str]]:
    """Each policy's repeats as strings of 0/1 in episode order
    (:func:`~sword_jax.rl.env_rollout.outcomes_text`, as ``success_summary`` keeps them)."""
    from sword_jax.rl.env_rollout import outcomes_text

    return {p: [outcomes_text(o) for o in runs] for p, runs in outcomes.items() if runs}


def comparison_from_strings(repeats: dict[str, list[str]]) -> dict:
    """:func:`compare_repeats` per policy from :func:`outcome_strings`'s form (read back by
    :func:`~sword_jax.rl.env_rollout.point_outcomes`)."""
    from sword_jax.rl.env_rollout import point_outcomes

    return {p: compare_repeats([point_outcomes({"outcomes": r}) for r in runs]) for p, runs in repeats.items()}


def load_result(path: str) -> dict:
    """A saved ``eval_repeat.json``, checked: its policies compared again from its outcomes (where it has them),
    with at least two repeats. Raises :class:`~sword_jax.cli.UsageError` naming what is wrong."""
    try:
        with open(path) as f:
            result = json.load(f)
    except OSError as e:
        raise cli.UsageError(f"--from {path}: cannot read it ({e.strerror or e})") from e
    except json.JSONDecodeError as e:
        raise cli.UsageError(f"--from {path}: not JSON ({e})") from e
    if not isinstance(result, dict) or not isinstance(result.get("policies"), dict):
        raise cli.UsageError(f"--from {path}: not an eval_repeat.json (no 'policies')")
    if result.get("outcomes"):
        try:
            result["policies"] = comparison_from_strings(result["outcomes"])
        except ValueError as e:
            raise cli.UsageError(f"--from {path}: {e}") from e
    if not result["policies"]:
        raise cli.UsageError(f"--from {path}: fewer than 2 repeats finished, nothing to compare")
    return result


def result_key(result: dict) -> str:
    """``latest.json``'s key for ``result``: one for evaluations with XLA's deterministic ops, one for plain ones."""
    return "mjx_eval_repeat_deterministic_small" if result.get("deterministic") else "mjx_eval_repeat_small"


def record_result(result: dict) -> dict:
    """The entry of ``result`` (as :func:`main` writes it; key :func:`result_key`) merged into ``latest.json``,
    stamped with the device and command that ran the evaluation."""
    from benchmarks import common

    key = result_key(result)
    worst = max(s for c in result["policies"].values() for s in c["differing_share"])
    entry = common.record(key, worst, 0.0, unit="largest share of episodes whose outcome "
                          "differed between repeats of the same evaluation", config=result.get("config"),
                          deterministic=result.get("deterministic"), policies=result["policies"],
                          seconds=result.get("seconds"), complete=result.get("complete", True))
    for stamp in ("device", "command"):  # those of the run that evaluated
        if result.get(stamp):
            entry[stamp] = result[stamp]
    common.merge_results({key: entry})
    return entry


def parse(argv: Sequence[str]) -> tuple[argparse.Namespace, list[str]]:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0],
                                epilog="Other --rl.section.key=value arguments are config overrides.")
    parser.add_argument("--config", default="sword:small", help="the experiment config (default sword:small)")
    parser.add_argument("--policy", help="the policy's parameters (.npz, as bench_policy --policy)")
    parser.add_argument("--out", help="folder for eval_repeat.json")
    parser.add_argument("--from", dest="from_file", metavar="FILE",
                        help="record this saved eval_repeat.json (with --record) instead of evaluating")
    parser.add_argument("--repeats", type=int, default=3, help="evaluations of the same policy (>= 2)")
    parser.add_argument("--episodes-per-task", type=int, default=50, help="evaluation episodes per task (1-50)")
    parser.add_argument("--deterministic", action="store_true",
                        help=f"add {DETERMINISTIC_FLAG} to XLA_FLAGS (GPU) before JAX starts its backend")
    parser.add_argument("--record", action="store_true", help="write mjx_eval_repeat_small (deterministic: "
                        "mjx_eval_repeat_deterministic_small) to latest.json")
    args, rest = parser.parse_known_args(argv)
    if args.from_file is not None:
        if not args.record:
            raise cli.UsageError("--from only records a saved result: add --record")
        if args.policy or args.out or rest:
            raise cli.UsageError("--from evaluates nothing: drop --policy, --out and config overrides")
        return args, rest
    if args.policy is None or args.out is None:
        raise cli.UsageError("--policy and --out are needed to evaluate (or --from FILE --record)")
    if args.repeats < 2:
        raise cli.UsageError(f"--repeats must be >= 2 (a repeat is compared with the first), got {args.repeats}")
    if not 1 <= args.episodes_per_task <= 50:
        raise cli.UsageError(f"--episodes-per-task must be in 1..50 (the tasks' fixed evaluation states), got "
                             f"{args.episodes_per_task}")
    if not os.path.isfile(args.policy):
        raise cli.UsageError(f"--policy {args.policy}: no such file")
    bad = cli.not_dotted_overrides(rest)
    if bad:
        raise cli.UsageError(f"not a dotted config override (--section.key=value): {' '.join(bad)}")
    return args, rest


def main(argv: Sequence[str] | None = None) -> dict:
    argv = sys.argv[1:] if argv is None else list(argv)
    args, overrides = parse(argv)
    if args.from_file is not None:
        result = load_result(args.from_file)
        entry = record_result(result)
        print(f"[eval-repeat] recorded {args.from_file}: largest share of differing episodes {entry['value']:.3f}")
        return result
    if args.deterministic:  # read when the backend starts: before any JAX computation below
        os.environ["XLA_FLAGS"] = with_flag(os.environ.get("XLA_FLAGS", ""), DETERMINISTIC_FLAG)

    import jax

    import configs
    from benchmarks import common
    from sim import tasks as sim_tasks
    from sim.mjx_batch import MjxEpisodes, episode_starts
    from sword_jax.rl.jax_env_grpo import EnvGRPO
    from sword_jax.rl.params_io import load_params_npz
    from sword_jax.rl.policy import build_policy, tokenize_instructions

    cfg, rest = configs.from_argv(["--config", args.config, *overrides])
    if rest:
        raise cli.UsageError(f"bench_eval_repeat: arguments not understood: {' '.join(rest)}")
    rl = cfg.rl
    graphdef, params = build_policy(rl, seed=cfg.seed)
    params = load_params_npz(args.policy, params)
    episodes = sim_tasks.evaluation_episodes(list(cfg.sim.tasks), args.episodes_per_task)
    qpos, text = episode_starts(episodes)
    runner = EnvGRPO(graphdef, rl, MjxEpisodes(cfg.sim, resolution=cfg.sim.resolution), max_steps=cfg.sim.max_steps,
                     starts_at=None, eval_starts=qpos, eval_tokens=tokenize_instructions(text, rl.policy.max_instruction_bytes),
                     eval_tasks=[t for t, _ in episodes], key=jax.random.key(cfg.seed))
    os.makedirs(args.out, exist_ok=True)
    runner.start_probe(params, os.path.join(args.out, "probe"))
    result = {"policy": args.policy, "config": cfg.name, "overrides": overrides, "device": common.device_name(),
              "xla_flags": os.environ.get("XLA_FLAGS", ""), "deterministic": args.deterministic,
              "rollout_batch": rl.grpo.rollout_batch * rl.grpo.group_size, "repeats_asked": args.repeats,
              "command": common.command_line()}
    path = os.path.join(args.out, "eval_repeat.json")

    def save(outcomes, seconds):  # after every repeat: a run cut off keeps what it finished
        kept = outcome_strings(outcomes)
        result.update(complete=len(seconds) == args.repeats, seconds=list(seconds), outcomes=kept,
                      policies=comparison_from_strings(kept) if len(seconds) >= 2 else {})
        write_json_atomic(path, result)

    repeat_evaluations(runner, params, args.repeats, masked=rl.env.proprio == "missing", on_repeat=save)
    for policy, c in result["policies"].items():
        print(f"[eval-repeat] {policy}: success {', '.join(f'{s:.3f}' for s in c['success'])}; episodes differing "
              f"from the first repeat {', '.join(str(d) for d in c['differing'])} of {c['episodes']}", flush=True)
    if args.record:
        record_result(result)
    return result


if __name__ == "__main__":
    cli.run(main)
