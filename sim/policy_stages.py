"""Pipeline stages: reward model, supervised policy, then GRPO inside the world model with simulator evaluation
(and GRPO against the ground truth, the reference ``train.compare`` runs beside it).

Each part is the function its entry point (``train.train_reward``, ``train.train_policy``, ``train.grpo``)
calls: :func:`sim.reward_training.run_reward_model`, :func:`sim.policy_training.run_sft_policy` and
:func:`sim.grpo_training.run_grpo`, called here with the pipeline's typed config and work dir. They are three stages so
that each resumes on its own and so that runs which differ only in the world model
(``train.compare``) can share the reward model and the supervised policy. The success curve (before
and during GRPO, in the MuJoCo environments) lands in ``<workdir>/rl/grpo/success_curve.{json,png}``.
"""

from __future__ import annotations

import os

from sword_jax.pipeline.grpo import GRPOInputs, training_success
from sword_jax.pipeline.stages import Context, cpu_workers


def _scalars(result: dict) -> dict:
    """The plain numbers of a part's result (nested dicts flattened one level)."""
    out = {}
    for key, value in result.items():
        if isinstance(value, (int, float, str, bool)):
            out[key] = value
        elif isinstance(value, dict):
            for sub, inner in value.items():
                if isinstance(inner, (int, float)):
                    out[f"{key}.{sub}"] = inner
    return out


def _demos(ctx: Context) -> str:
    """The policy's demonstrations (they end at success); older work dirs only have the training file."""
    data = ctx.results["data"]
    return data["demos"]["path"] if "demos" in data else data["train"]["path"]


def reward_model(ctx: Context) -> dict:
    """The success detector, on the demonstrations plus the supervised policy's own rollouts where the
    pipeline made them: its failures are the negatives a detector rewarding that policy must know.
    With ``rl.reward_model.labels=state`` the world model's fixed-length expert episodes join them: they
    keep going after success, so they hold the solved frames (and frames solved and then undone)
    that episodes ending at their success never show."""
    from sim import reward_training

    files = [_demos(ctx)]
    train_file = ctx.results["data"]["train"]["path"]
    if ctx.cfg.rl.reward_model.labels == "state" and train_file != files[0]:
        files.append(train_file)
    rollouts = ctx.results.get("policy_data", {}).get("path")
    if rollouts:
        files.append(rollouts)
    return _scalars(reward_training.run_reward_model(ctx.cfg_in(ctx.workdir), files))


def sft_policy(ctx: Context) -> dict:
    from sim import policy_training

    if ctx.cfg.rl.sft.init:
        return policy_training.given_policy(ctx.cfg_in(ctx.workdir), ctx.cfg.rl.sft.init)
    return _scalars(policy_training.run_sft_policy(ctx.cfg_in(ctx.workdir), [_demos(ctx)]))


def grpo_in_world_model(ctx: Context) -> dict:
    from sim import grpo_training

    inputs = GRPOInputs(demos=(_demos(ctx),), world_model=ctx.results["world_model"]["workdir"],
                        vae=ctx.results["vae"]["path"], policy=ctx.results["sft_policy"]["path"],
                        reward=ctx.results["reward_model"]["path"],
                        light_decoder=ctx.results.get("light_decoder", {}).get("path") or "")
    result = grpo_training.run_grpo(ctx.cfg_in(ctx.workdir), inputs, simulator="world_model", env_workers=cpu_workers())
    return {"reward_model": _summary(ctx.results["reward_model"]), **_policy_result(ctx, result)}


def grpo_in_ground_truth(ctx: Context) -> dict:
    """GRPO against the MuJoCo environments themselves, from the same supervised policy: the upper
    reference for GRPO in a learned simulator (``train.compare``'s ``ground_truth`` run). It needs only
    the demonstrations and the supervised policy; rollouts follow ``rl.env``."""
    from sim import grpo_training

    inputs = GRPOInputs(demos=(_demos(ctx),), policy=ctx.results["sft_policy"]["path"])
    result = grpo_training.run_grpo(ctx.cfg_in(ctx.workdir), inputs, simulator="env", env_workers=cpu_workers())
    return _policy_result(ctx, result)


def _summary(stage_result: dict) -> dict:
    """An earlier stage's result as a GRPO record keeps it: without its time and checkpoint path."""
    return {k: v for k, v in stage_result.items() if k not in ("seconds", "path")}


def _policy_result(ctx: Context, result: dict) -> dict:
    """A GRPO stage's record: the supervised policy it started from, its run and real success per step."""
    success = {f"grpo step {p['step']}": p["mean"] for p in result["curve"]}
    return {
        "sft": _summary(ctx.results["sft_policy"]),
        "grpo": {"steps": ctx.cfg.rl.grpo.steps, "workdir": result["workdir"],
                 "training_success": training_success(result.get("history", []))},
        "success": success,
        "success_curve_png": os.path.join(result["workdir"], "success_curve.png"),
    }
