"""Pipeline stage: reward model, supervised policy, GRPO inside the world model, simulator evaluation.

Each part is its own entry point (``train.train_reward``, ``train.train_policy``, ``train.grpo``),
run here on the pipeline's config with its work dir; the success curve (before and during GRPO, in
the MuJoCo environments) lands in ``<workdir>/rl/grpo/success_curve.{json,png}``.
"""

from __future__ import annotations

import os

from train.stagerunner import Context


def _scalars(result: dict) -> dict:
    """The plain numbers of an entry point's result (nested dicts flattened one level)."""
    out = {}
    for key, value in result.items():
        if isinstance(value, (int, float, str, bool)):
            out[key] = value
        elif isinstance(value, dict):
            for sub, inner in value.items():
                if isinstance(inner, (int, float)):
                    out[f"{key}.{sub}"] = inner
    return out


def run(ctx: Context) -> dict:
    from train import grpo, train_policy, train_reward

    demos = ctx.results["data"]["train"]["path"]
    base = ["--config", ctx.cfg_name, *ctx.overrides, f"--workdir={ctx.workdir}"]
    reward = train_reward.main(base + ["--demos", demos])
    sft = train_policy.main(base + ["--demos", demos])
    rl_dir = os.path.join(ctx.workdir, "rl")
    result = grpo.main(base + [
        "--simulator", "world_model", "--demos", demos,
        "--world-model", ctx.results["world_model"]["workdir"], "--vae", ctx.results["vae"]["path"],
        "--policy", os.path.join(rl_dir, "policy_sft"), "--reward", os.path.join(rl_dir, "reward_model"),
    ])
    success = {f"grpo step {p['step']}": p["mean"] for p in result["curve"]}
    return {
        "reward_model": _scalars(reward),
        "sft": _scalars(sft),
        "grpo": {"steps": ctx.cfg.rl.grpo_steps, "workdir": result["workdir"]},
        "success": success,
        "success_curve_png": os.path.join(result["workdir"], "success_curve.png"),
    }
