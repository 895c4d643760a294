"""Generates the tables of figures in README.md and docs/RESULTS.md from the committed result JSON.

    python -m benchmarks.report            # rewrite every generated table between its markers
    python -m benchmarks.report --check    # exit 1 naming the tables that disagree with the JSON

A generated table sits between ``<!-- table:NAME -->`` and ``<!-- /table:NAME -->``; NAME is a key of
``TABLES``, whose function builds the table from ``benchmarks/results/`` (``latest.json``, the comparison
folders under ``compare/`` and the files under ``policy/``). The prose around the tables is written by
hand; a figure that changes in the JSON changes here only by rerunning this command.
"""

from __future__ import annotations

import json
import os
import re
import statistics
from collections.abc import Callable, Iterator, Sequence

from sword_jax import cli

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS_DIR = os.path.join(ROOT, "benchmarks", "results")
DOCUMENTS = ("README.md", os.path.join("docs", "RESULTS.md"))
HEADLINE = ("imagined_frames_per_s_5b_full", "dit_train_mfu_5b_full_h200", "dit_train_mfu_vs_measured_peak",
            "dit_train_levers", "dlb_overhead_ratio", "vae_decode_frames_per_s", "vae_decode_chunk_frames_per_s",
            "vae_encode_frames_per_s", "imagined_frames_per_s_5b_width", "mjx_env_steps_per_s_128px",
            "latent_cache_gb_paper_dataset")
_BLOCK = re.compile(r"(<!-- table:([\w-]+) -->\n)(.*?)(<!-- /table:\2 -->)", re.S)


def _load(*parts: str) -> dict:
    with open(os.path.join(RESULTS_DIR, *parts)) as f:
        return json.load(f)


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _device(entry: dict) -> str:
    """``NVIDIA H100 80GB HBM3 x1 (gpu)`` -> ``1 x H100``."""
    text = str(entry.get("device", ""))
    match = re.match(r"NVIDIA (H\d+)\S*(?: [^x]*)? x(\d+)", text)
    return f"{match.group(2)} x {match.group(1)}" if match else text


def _step_span(entry: dict) -> str:
    """The steps an entry's runs reached, ``14-17`` (or ``15`` where all reached the same)."""
    steps = sorted(r["steps"] for r in entry["runs"].values())
    return f"{steps[0]}-{steps[-1]}" if steps[0] != steps[-1] else str(steps[0])


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _span(values, digits: int = 1) -> str:
    """``0.2-1.4%``: the smallest and largest of shares, in percent."""
    values = [100 * v for v in values]
    return f"{min(values):.{digits}f}-{max(values):.{digits}f}%"


def _pct(x: float) -> str:
    return f"{100 * x:+.1f}"


def _ci(figure: dict) -> str:
    """A success figure (``mean``, ``ci95``) as ``mean [low, high]`` (``benchmarks.common.interval_text``, which
    this module does not import: it loads jax)."""
    return f"{figure['mean']:.3f} [{figure['ci95'][0]:.3f}, {figure['ci95'][1]:.3f}]"


def _interval(ci, scale: float = 100.0) -> str:
    return f"[{scale * ci[0]:+.1f}, {scale * ci[1]:+.1f}]"


# --- README ---------------------------------------------------------------------------------------------

def _first_half_world_model_text() -> str:
    """The README's words for GRPO in Sword's world model from first-half keyframes (``FIRST_HALF_WORLD_MODEL``):
    the gains of the policy it trains with each rollout paid by reality, at the runs' last evaluation, and ground
    truth's at the same step; empty where the record is absent."""
    path = os.path.join(RESULTS_DIR, *FIRST_HALF_WORLD_MODEL, "grpo_reward_source.json")
    if not os.path.exists(path):
        return ""
    arm = _load(*FIRST_HALF_WORLD_MODEL, "grpo_reward_source.json")["arms"]["exec"]
    step = arm["steps"]
    truth = [_step_gain(points, step, "sampled_as_trained") for _, points, _ in
             _seed_runs(os.path.join(RESULTS_DIR, *FIRST_HALF_AS_TRAINED, "centred", "gt"))]
    gains = ", ".join(_pct(g) for g in arm["as_trained_gain_per_seed"].values())
    beside = f" ({_pct(min(t[0] for t in truth))} or more in {step})" if truth and None not in truth else ""
    return f"{beside}; Sword's world model, paid by reality, {gains} in {step}"


def _closed_loop_noise_text(entry: dict) -> str:
    """The README's figure of a ``world_model_closed_loop_small`` entry: per setting (the reference first, each named
    by its overrides' values) the frame error at the last decision and the detector's false successes, and what
    reality paid the imagined actions against the policy on real frames."""
    settings = sorted(entry["settings"].values(), key=lambda v: ("vs_first" in v, v["overrides"]))
    keys = ", ".join(o.split("=", 1)[0] for o in settings[0]["overrides"])
    names = " / ".join(", ".join(o.split("=", 1)[1] for o in v["overrides"]) for v in settings)
    errors = " / ".join(f"{v['frame_error'][1]:.3f}" for v in settings)
    false = " / ".join(f"{100 * v['false_success_share']:.1f}%" for v in settings)
    return (f"`{keys}` {names}: frame error at decision {settings[0]['decisions'][1]} {errors}; false successes "
            f"{false}; real success {_span([v['paid'] for v in settings])} (on real frames {100 * entry['real']:.1f}%)")


def readme_results() -> str:
    """The README's one results table: a headline figure per topic, linked to its section."""
    latest = _load("latest.json")
    doc = "docs/RESULTS.md"
    dlb = latest["world_model_dlb_vs_teacher_forcing_small"]["value"]
    aug = latest["world_model_augmentation_vs_none_mixed_small"]["value"]
    arms = latest["policy_grpo_sword_vs_wovr_unrefreshed_small"]["value"]
    gt = latest["policy_grpo_ground_truth_gain_small"]
    sword, wovr = latest["policy_grpo_world_model_gain_small"], latest["policy_grpo_wovr_world_model_refreshed_gain_small"]
    full5b, light5b = latest["imagined_frames_per_s_5b_full"], latest["imagined_frames_per_s_5b_full_light_decoder"]
    setting = latest.get("policy_grpo_ground_truth_learned_setting_gain_small")
    source = latest.get("policy_grpo_reward_source_small")
    noise = latest.get("policy_grpo_branched_open_small", {}).get("contrasts", {}).get("success")
    rest = latest.get("policy_grpo_rest_h12_small", {}).get("arms", {}).get("success")  # 12 decisions from rest
    # ground truth in the learned simulator's setting, judged by the policy it trains (4 actions a chunk)
    first_half = latest.get("policy_grpo_ground_truth_as_trained_small", {}).get("arms", {}).get("gt")
    loop = latest.get("world_model_closed_loop_small")  # bench_closed_loop: one world model, several samplers
    fidelity = _load(*SIM_FIDELITY, "summary.json")["variants"]  # the policy through each VAE alone (4 GPUs)
    base, vae8x = fidelity["base"]["view"], fidelity["vae8x"]["view"]
    exec_runs, gt_runs = ([[r for r in source["runs"].values() if r["arm"] == arm] for arm in ("exec", "gt")]
                          if source else ([], []))
    rows = [
        ("Claim 1: DLB vs teacher forcing, `small`, 3 seeds",
         f"latent MSE {dlb['original_latent_mse'][0]:.3f} vs {dlb['original_latent_mse'][1]:.3f} (Original), "
         f"{dlb['original_latent_mse_frames_61_68'][0]:.3f} vs {dlb['original_latent_mse_frames_61_68'][1]:.3f} "
         "at frames 61-68", "world_model_dlb_vs_teacher_forcing_small",
         f"[figure](benchmarks/results/compare/small/dlb_vs_teacher_forcing.png), "
         f"[section]({doc}#claim-1-dlb-vs-teacher-forcing)"),
        ("Claim 2: style augmentation vs none, LIBERO-Mixed",
         f"LPIPS {aug['lpips'][0]:.3f} vs {aug['lpips'][1]:.3f}, latent MSE {aug['latent_mse'][0]:.3f} vs "
         f"{aug['latent_mse'][1]:.2f}, FVD {aug['fvd'][0]:.0f} vs {aug['fvd'][1]:.0f}",
         "world_model_augmentation_vs_none_mixed_small",
         f"[figure](benchmarks/results/compare/small/augmentation_vs_none.png), "
         f"[section]({doc}#claim-2-style-augmentation-vs-none)"),
        ("Claim 3: GRPO in Sword vs in WoVR, real success after 50 steps",
         f"mean gain Sword {_pct(arms['sword'])}, WoVR {_pct(arms['wovr'])}, MuJoCo itself "
         f"{_pct(arms['ground_truth_reference'])} points", "policy_grpo_sword_vs_wovr_unrefreshed_small",
         f"[figure](benchmarks/results/compare/small_grpo/grpo_sword_vs_wovr.png), "
         f"[section]({doc}#claim-3-grpo-in-sword-vs-in-wovr)"),
        ("Supervised policy of the pipeline (500 episodes)",
         f"success {latest['policy_sft_success_pipeline_small']['value']:.3f}", "policy_sft_success_pipeline_small",
         f"[section]({doc}#policies-in-the-ground-truth-environments)"),
        ("Ground-truth GRPO on MJX, 3 seeds",
         f"sampled policy {_pct(gt['sampled_min_gain'])} points or more in {gt['steps']} steps; greedy "
         f"{_pct(gt['greedy_min_gain'])} or more", "policy_grpo_ground_truth_gain_small",
         f"[figure]({gt['data'].split('{')[0]}grpo_ground_truth_seeds.png), "
         f"[section]({doc}#policies-in-the-ground-truth-environments)"),
        ("GRPO in the refreshed learned simulators, 3 seeds",
         f"sampled policy: Sword {', '.join(_pct(r['sampled']['gain']) for r in sword['per_seed'].values())}, WoVR "
         f"config {', '.join(_pct(r['sampled']['gain']) for r in wovr['per_seed'].values())} points in "
         f"{sword['steps']}-{max(r['steps'] for r in sword['per_seed'].values())} steps (target +10)",
         "policy_grpo_world_model_gain_small", f"[section]({doc}#refreshing-the-simulator-while-the-policy-moves)"),
        *([("GRPO in the learned simulator's setting",
            f"real frames and reward {_pct(setting['value'])} points or more in {setting['steps']} steps "
            f"({_device(setting)}); Sword's frames "
            f"{_span(r['paid_success']['first'] for r in exec_runs)} (real "
            f"{_span([r['paid_success']['first'] for r in gt_runs], 0)}); through the VAE "
            f"{base['vae']['mean']:.3f} vs {base['real']['mean']:.3f}, the 8x VAE {vae8x['vae']['mean']:.3f} vs "
            f"{vae8x['real']['mean']:.3f} ({base['real']['episodes']} episodes)",
            "policy_grpo_reward_source_small", f"[section]({doc}#frames-or-reward)")] if setting and source else []),
        *([("Short GRPO rollouts branched from real states (MJX), 3 seeds",
            f"gain minus a noise-only control's: {_pct(noise['sampled']['mean'])} "
            f"{_interval(noise['sampled']['ci95'])} (true proprio), {_pct(noise['sampled_proprio_masked']['mean'])} "
            f"{_interval(noise['sampled_proprio_masked']['ci95'])} (proprio masked) points in {noise['steps']} steps",
            "policy_grpo_branched_open_small", f"[section]({doc}#frames-or-reward)")] if noise else []),
        *([("GRPO rollouts from rest cut at 12 decisions (MJX), 3 seeds",
            f"sampled policy, proprio masked: {', '.join(_pct(g) for g in rest['masked_gain_per_seed'].values())} "
            f"points by steps {_step_span(latest['policy_grpo_rest_h12_small'])} (mean {_pct(rest['mean'])}); from "
            "open starts the same rollouts had gained at one seed", "policy_grpo_rest_h12_small",
            f"[section]({doc}#frames-or-reward)")] if rest else []),
        *([("GRPO from first-half keyframes, 12 x 4, 3 seeds",
            "sampled, as trained (4-action chunks, no proprio): MJX "
            f"{', '.join(_pct(g) for g in first_half['as_trained_gain_per_seed'].values())} points in "
            f"{first_half['steps']} steps" + _first_half_world_model_text(),
            "policy_grpo_ground_truth_as_trained_small", f"[section]({doc}#frames-or-reward)")] if first_half else []),
        *([("World model's closed loop, by sampler noise",
            _closed_loop_noise_text(loop), "world_model_closed_loop_small",
            f"[table]({doc}#frames-or-reward)")] if loop else []),
        ("MJX env-steps/s, 128 px, camera rendered",
         f"{latest['mjx_env_steps_per_s_128px']['value']:,.0f} (target 20,000)", "mjx_env_steps_per_s_128px",
         f"[section]({doc}#simulator-and-renderer)"),
        ("Imagined frames/s, full 5B model",
         f"{full5b['value']:.1f} (target {full5b['target']:.0f}); with the light decoder {light5b['value']:.1f} "
         f"(stretch {light5b['target']:.0f})", "imagined_frames_per_s_5b_full",
         f"[section]({doc}#the-full-5b-model)"),
        ("DiT training MFU, full 5B model", f"{latest['dit_train_mfu_5b_full_h200']['value']:.3f} (target 0.55)",
         "dit_train_mfu_5b_full_h200", f"[section]({doc}#the-full-5b-model)"),
        *([("Several GPUs: 4 of one host",
            f"5B FSDP MFU {latest['dit_train_mfu_5b_full_4gpu']['value']:.3f} (target 0.55); `small` data-parallel "
            f"scaling {latest['dp_scaling_efficiency_small_4gpu']['value']:.3f} of the fastest one-GPU step "
            f"(target 0.90); one process per GPU "
            f"killed and resumed {'bit-identical' if latest['multiprocess_resume_exact']['value'] else 'NOT exact'}",
            ("dit_train_mfu_5b_full_4gpu", "dp_scaling_efficiency_small_4gpu", "multiprocess_resume_exact"),
            f"[section]({doc}#several-gpus)")]
          if all(k in latest for k in ("dit_train_mfu_5b_full_4gpu", "dp_scaling_efficiency_small_4gpu",
                                       "multiprocess_resume_exact")) else []),
        ("DLB step overhead vs teacher forcing", f"{100 * latest['dlb_overhead_ratio']['value']:+.1f}% (target 3%)",
         "dlb_overhead_ratio", f"[section]({doc}#the-full-5b-model)"),
    ]
    def run(keys) -> str:  # a row of several entries: the first one's device, every date they were measured on
        keys = (keys,) if isinstance(keys, str) else keys
        return f"{_device(latest[keys[0]])}, {', '.join(sorted({latest[k]['date'] for k in keys}))}"

    return _table(["result", "figure", "run", "details"], [[what, figure, run(keys), link]
                                                            for what, figure, keys, link in rows])


# --- docs/RESULTS.md ------------------------------------------------------------------------------------

_CLAIM1 = (("latent_mse", "latent MSE", "{:.3f}"), ("probe_ee_cm", "end-effector error (cm)", "{:.2f}"),
           ("probe_gripper_agree", "gripper agreement", "{:.3f}"),
           ("reward_agree", "imagined-vs-real success agreement", "{:.3f}"), ("lpips", "LPIPS", "{:.3f}"),
           ("fvd", "FVD", "{:.0f}"), ("psnr", "PSNR", "{:.2f}"))
_CLAIM2 = (("lpips", "LPIPS", "{:.3f}"), ("flolpips", "FloLPIPS", "{:.3f}"), ("psnr", "PSNR", "{:.2f}"),
           ("ssim", "SSIM", "{:.3f}"), ("latent_mse", "latent MSE", "{:.3f}"),
           ("probe_ee_cm", "end-effector error (cm)", "{:.2f}"), ("probe_gripper_agree", "gripper agreement", "{:.3f}"),
           ("fvd", "FVD", "{:.0f}"))


def _comparison_rows(comparison: dict, pair: str, runs: tuple[str, str], labels: tuple[str, str],
                     columns, splits: tuple[str, ...]) -> list[list[str]]:
    rows = []
    for split in splits:
        for run, label in zip(runs, labels):
            metrics = comparison["runs"][run]["metrics"]
            rows.append([f"{split.capitalize()}, {label}"] + [
                fmt.format(metrics[f"{split}/{key}"]["mean"]) + (
                    " ± " + fmt.format(metrics[f"{split}/{key}"]["std"]) if key == "latent_mse" else "")
                for key, _, fmt in columns])
        paired = comparison["paired"][pair]
        rows.append([f"{labels[0]} better at"] + [
            f"{paired[f'{split}/{key}']['ours_better']}/{paired[f'{split}/{key}']['n']}" for key, _, _ in columns])
    return rows


def claim1() -> str:
    """DLB (`sword`) vs teacher forcing, mean (± std for latent MSE) over seeds, and at how many seeds DLB won."""
    comparison = _load("compare", "small", "comparison.json")
    return _table([""] + [name for _, name, _ in _CLAIM1],
                  _comparison_rows(comparison, "sword vs teacher_forcing", ("sword", "teacher_forcing"),
                                   ("DLB", "teacher forcing"), _CLAIM1, ("original", "mixed")))


def claim2() -> str:
    """Style augmentation (`sword`) vs none on LIBERO-Mixed."""
    comparison = _load("compare", "small", "comparison.json")
    return _table([""] + [name for _, name, _ in _CLAIM2],
                  _comparison_rows(comparison, "sword vs no_augmentation", ("sword", "no_augmentation"),
                                   ("augmentation", "none"), _CLAIM2, ("mixed",)))


def claim3() -> str:
    """Real success at GRPO steps 0 / 25 / 50 per seed, and the gain with its Newcombe interval."""
    paired = _load("compare", "small_grpo", "comparison.json")["paired"]["sword vs wovr"]
    names = {"sword": "the Sword world model", "wovr": "the WoVR world model",
             "ground_truth": "MuJoCo itself (reference)"}
    rows = []
    for run, name in names.items():
        for i, seed in enumerate(paired["seeds"]):
            success = _load("compare", "small_grpo", f"{run}_seed{seed}.json")["success"]
            steps = [success[f"grpo step {s}"] for s in (0, 25, 50)]
            gain = paired[run][i]
            rows.append([name, str(seed)] + [f"{s:.3f}" for s in steps] +
                        [f"{_pct(gain)} {_interval(paired['gain_ci95'][run][i])}"])
    return _table(["GRPO in", "seed", "step 0", "step 25", "step 50", "gain, points (95% Newcombe)"], rows)


def proprio_modes() -> str:
    """One supervised policy's real success with each proprio input a learned simulator can give it."""
    entry = _load("latest.json")["policy_sft_success_by_proprio_mode_small"]
    labels = {"true": "the true proprio (every real evaluation)",
              "missing": "no proprio (`missing`: what GRPO in the world model trains)",
              "reckoned": "proprio dead-reckoned from its own executed actions (`reckoned`)"}
    rows = [[label, f"{entry['by_mode'][mode]['success']:.3f}",
             "[{:.3f}, {:.3f}]".format(*entry["by_mode"][mode]["ci95"])] for mode, label in labels.items()]
    return _table([f"the policy reads ({entry['episodes']} episodes)", "success", "95% interval"], rows)


def reward_labels() -> str:
    """The success detector trained on the demonstrations' last frames vs on each frame's true state."""
    labels = _load("policy", "reward_labels.json")["labels"]
    names = {"tail": "last 8 frames before success (`tail`)", "state": "each frame's success predicate (`state`)"}
    rows = [[names[name], f"{entry['frame_precision']:.2f}", f"{entry['frame_recall']:.2f}",
             f"{100 * entry['fires_on_failed']:.0f}%", f"{100 * entry['fires_early']:.0f}%",
             f"{entry['mean_lead_frames']:.1f}"] for name, entry in labels.items() if name in names]
    return _table(["detector labels", "frame precision", "frame recall", "fires on a failed episode",
                   "fires > 4 frames before the bowl lands", "mean lead (frames)"], rows)


def reward_detector_on_policy() -> str:
    """The state-labelled detector on the post-trained policy's own held-out episodes and on noisy experts',
    trained on experts alone and with the policy's rollouts, under the k-consecutive-frames success rule."""
    run = _load("policy", "reward_labels.json")["policy_episodes"]
    names = {"experts": "experts", "experts_and_policy": "experts + 20 policy episodes per task"}
    rows = []
    for name, detector in run["detectors"].items():
        for k in (str(k) for k in run["success_frames"]):
            mine, theirs = detector["policy_heldout"][k], detector["expert_heldout"][k]
            rows.append([names.get(name, name), k, f"{100 * mine['fires_on_failed']:.0f}%", f"{100 * mine['misses']:.0f}%",
                         f"{mine['frame_precision']:.2f} / {mine['frame_recall']:.2f}", f"{mine['separation']:+.2f}",
                         f"{100 * theirs['fires_on_failed']:.0f}% / {100 * theirs['misses']:.0f}%"])
    return _table(["trained on", "k", "policy: fires on failed", "policy: misses", "policy: frame precision / recall",
                   "policy: separation", "noisy experts: fires on failed / misses"], rows)

# the detector at other frame sizes and widths, on the same episodes (bench_reward_labels --policy with overrides)
DETECTOR_SIZES = (("reward_labels.json", "64 px, width 16"), ("reward_labels_detector128.json", "128 px, width 16"),
                  ("reward_labels_detector128_w32.json", "128 px, width 32"))


def reward_detector_sizes() -> str:
    """The policy's held-out episodes judged by detectors reading 64 or 128 px frames (and a wider one):
    false and missed successes and separation at k = 1 and 4 consecutive frames."""
    names = {"experts": "experts", "experts_and_policy": "experts + policy episodes"}
    rows = []
    for file, label in DETECTOR_SIZES:
        if not os.path.exists(os.path.join(RESULTS_DIR, "policy", file)):
            continue
        run = _load("policy", file)["policy_episodes"]
        for name, detector in run["detectors"].items():
            cells = []
            for k in ("1", "4"):
                r = detector["policy_heldout"][k]
                cells.append(f"{100 * r['fires_on_failed']:.0f}% / {100 * r['misses']:.0f}% / {r['separation']:+.2f}")
            rows.append([label, names.get(name, name), *cells])
    return _table(["detector", "trained on", "k = 1: fires on failed / misses / separation",
                   "k = 4: the same"], rows)

def grpo_arms() -> str:
    """Ground-truth GRPO from the pipeline's supervised policy: greedy and sampled success per arm."""
    arms = _load("policy", "grpo_arms_small_h200.json")["arms"]
    rows = []
    for name, arm in arms.items():
        greedy = " / ".join(f"{p['success']:.3f}" for p in arm["greedy"])
        sampled = " / ".join(f"{p['success']:.3f}" for p in arm.get("sampled") or []) or "not measured"
        gain = arm.get("greedy_gain")
        ci = arm.get("greedy_gain_ci95")
        rows.append([f"`{name}`", ", ".join(str(p["step"]) for p in arm["greedy"]), greedy, sampled,
                     f"{_pct(gain)} {_interval(ci)}" if gain is not None and ci else ""])
    return _table(["arm", "steps", "greedy success", "sampled success (at T)", "greedy gain, points"], rows)


def mjx_throughput() -> str:
    """MJX env-steps/s at 128 px against batch size (physics and rendering in one jit)."""
    entry = _load("latest.json")["mjx_env_steps_per_s_128px"]
    sweep = sorted(entry["sweep"], key=lambda row: row["batch"])
    rows = [["env-steps/s (physics + render, one jit)"] + [f"{r['env_steps_per_s']:,.0f}" for r in sweep],
            ["physics only, env-steps/s"] + [f"{r['physics_steps_per_s']:,.0f}" for r in sweep],
            ["renderer only, frames/s"] + [f"{r['render_frames_per_s']:,.0f}" for r in sweep]]
    return _table([f"{_device(entry)}, 128 px, {entry['date']}"] + [f"batch {r['batch']}" for r in sweep], rows)


def benchmarks() -> str:
    """Every recorded GPU figure of ``latest.json``: value, target, device, date and the command that made it."""
    results = _load("latest.json")
    keys = [k for k in HEADLINE if k in results] + sorted(
        k for k in results if k not in HEADLINE and "(cpu)" not in str(results[k].get("device", "")))
    rows = []
    for key in keys:
        entry = results[key]
        value = entry.get("value")
        rows.append([f"`{key}`", _fmt(value) if not isinstance(value, (dict, list)) else "see JSON",
                     _fmt(entry.get("target")), _device(entry), str(entry.get("date", "")),
                     f"`{entry.get('command') or entry.get('run_command', '')}`"])
    return _table(["figure", "value", "target", "device", "date", "command"], rows)


REFRESH_SUMMARY = ("policy", "grpo_refresh_small_4xh200", "grpo_refresh_summary.json")


def _refresh_label(name: str) -> str:
    head, _, seed = name.rpartition("_seed")
    variant, _, arm = head.rpartition("_")
    model = {"": "Sword", "wovr": "WoVR-config"}.get(variant, f"Sword ({variant})")
    return f"{model}{'' if arm == 'refreshed' else ', adapted once'}, seed {seed}"


def grpo_refresh_runs(where: tuple[str, ...] = REFRESH_SUMMARY) -> str:
    """GRPO in the refreshed world model: the sampled policy's real success at each evaluation, its gain,
    the greedy and proprio-masked policies; ground-truth GRPO's step 0 and step 10 for scale."""
    summary = _load(*where)
    steps = sorted({p["step"] for run in summary["runs"].values() for p in run["curve"]})
    rows = []
    for name, run in summary["runs"].items():
        by_step = {p["step"]: p["sampled"] for p in run["curve"]}
        s, g, m = run["sampled"], run["greedy"], run.get("sampled_proprio_masked")
        rows.append([_refresh_label(name)] + [f"{by_step[k]:.3f}" if k in by_step else "" for k in steps]
                    + [f"{s['gain']:+.3f} [{s['ci95'][0]:+.3f}, {s['ci95'][1]:+.3f}]",
                       f"{g['start']:.3f} -> {g['end']:.3f}",
                       f"{m['start']:.3f} -> {m['end']:.3f}" if m else "", str(run["real_episodes_used"])])
    gt = summary.get("ground_truth") or {}
    if gt:
        at = {k: [next((p["sampled"] for p in curve if p["step"] == k), None) for curve in gt.values()] for k in steps}
        last = max(k for k in steps if any(p["step"] == k for c in gt.values() for p in c))
        gains = [next(p["sampled"] for p in c if p["step"] == last) - c[0]["sampled"] for c in gt.values()
                 if any(p["step"] == last for p in c)]

        def span(values):
            values = [v for v in values if v is not None]
            return f"{min(values):.3f}-{max(values):.3f}" if values else ""

        rows.append([f"ground-truth GRPO, seeds 0-{len(gt) - 1} (for scale)"] + [span(at[k]) for k in steps]
                    + [f"{min(gains):+.3f} to {max(gains):+.3f} by step {last}" if gains else "", "", "", ""])
    return _table(["run"] + [f"step {k}" for k in steps]
                  + ["gain, 95% interval", "greedy", "proprio masked", "real episodes used"], rows)


def grpo_refresh_replay() -> str:
    """Each refresh's replay of the policy's new real episodes in the simulator GRPO trained in, and the
    refreshed detector's separation of real outcomes on held-out replays."""
    summary = _load(*REFRESH_SUMMARY)
    rows = []

    def sep(values: dict, h: str) -> str:
        v = values.get(h)
        return "" if v is None else f"{v:+.2f}"

    for name, run in summary["runs"].items():
        for r in run["refreshes"]:
            if r.get("skipped"):
                continue
            fs, ms = r["false_success_before"], r["missed_success_before"]
            rows.append([_refresh_label(name), str(r["step"]), f"{r['real_success']:.2f}", f"{fs['rate']:.2f}",
                         f"{ms['rate']:.2f}", f"{sep(r['separation_before'], '48')} / {sep(r['separation_before'], '96')}",
                         f"{r['threshold']:.3f}", sep(r["separation_after"], "48")])
    return _table(["run", "refresh at step", "real success", "real failures imagined successes",
                   "real successes imagined failures", "separation by 48 / 96 actions (before)", "threshold after",
                   "separation by 48 actions (after)"], rows)


CAUSES = ("policy", "grpo_refresh_causes_small_4xh200")
# each pipeline of the cause test and what it changed against the measured setting
CAUSE_VARIANTS = (("pipeline", "refreshed_seed0", "as measured (VAE without the perceptual loss, world model 3,000 steps)"),
                  ("pipeline_lpips", "lpips_refreshed_seed0", "VAE with the perceptual loss"),
                  ("pipeline_long", "long_refreshed_seed0", "world model 15,000 steps"),
                  ("pipeline_both", "both_refreshed_seed0", "both"))


def grpo_refresh_causes() -> str:
    """The cause test: Sword at seed 0 on four world models. Per world model: its final training loss, the
    first refresh's replay of the policy's real episodes before any GRPO step (false successes, separation of
    real outcomes), the refreshes whose simulator separated outcomes at the run's horizon, and the real gain."""
    summary = _load(*CAUSES, "grpo_refresh_summary.json")
    rows = []
    for folder, run_name, label in CAUSE_VARIANTS:
        run = summary["runs"][run_name]
        world_model = _load(*CAUSES, folder, "world_model.json")["results"]
        first = run["refreshes"][0]
        done = [r for r in run["refreshes"] if not r.get("skipped")]
        trusted = sum(bool(r["trust"]["trusted"]) for r in done)
        sb = first["separation_before"]
        s, g = run["sampled"], run["greedy"]
        real = [r["detector_real_frames"] for r in done if r.get("detector_real_frames")]
        precision = statistics.median(r["frame_precision"] for r in real) if real else float("nan")
        recall = statistics.median(r["frame_recall"] for r in real) if real else float("nan")
        rows.append([label, f"{world_model['final_metrics']['loss']:.3f}",
                     f"{first['false_success_before']['rate']:.2f}",
                     f"{sb.get('48', float('nan')):+.2f} / {sb.get('96', float('nan')):+.2f}",
                     f"{trusted} of {len(done)}", f"{precision:.2f} / {recall:.3f}", str(run["steps"]),
                     f"{s['gain']:+.3f} [{s['ci95'][0]:+.3f}, {s['ci95'][1]:+.3f}]", f"{g['start']:.3f} -> {g['end']:.3f}"])
    return _table(["world model", "world-model loss (last step)", "first refresh: real failures imagined successes",
                   "first refresh: separation by 48 / 96 actions", "refreshes trusted",
                   "refreshed detector on real frames at its threshold: precision / recall (median)", "GRPO steps",
                   "sampled gain, 95% interval", "greedy"], rows)


POLICY_DATA = ("policy", "grpo_refresh_policy_data_small_h200")
# the runs of the policy-data test, and the cause test's measured setting (expert data only) beside them
POLICY_DATA_RUNS = ((CAUSES, "refreshed_seed0", "expert demonstrations only (the cause test's measured setting)", "0.5"),
                    (POLICY_DATA, "refreshed_seed0", "with 20 rollouts per task of the post-trained policy", "0.5"),
                    (POLICY_DATA, "realdet_refreshed_seed0", "the same, detector fine-tuned on real frames only", "0"))


def _real_frames(report: dict | None) -> str:
    """A detector report on real frames as ``precision / recall / fires on failed episodes``."""
    if not report:
        return "not recorded"
    return f"{report['frame_precision']:.2f} / {report['frame_recall']:.2f} / {report['fires_on_failed']:.2f}"


def grpo_refresh_policy_data() -> str:
    """The first refresh of Sword's seed 0, with and without the post-trained policy's rollouts in the world
    model's and detector's data: the replay before the refresh (the pipeline's detector at the run's
    threshold), the calibration that followed and what it left, and the detector on the policy's real frames
    at the run's threshold before and after its fine-tune."""
    rows = []
    for where, run_name, label, share in POLICY_DATA_RUNS:
        first = _load(*where, "grpo_refresh_summary.json")["runs"][run_name]["refreshes"][0]
        sb, sa = first["separation_before"], first["separation_after"]
        calibration = first["calibration"]
        both = first.get("detector_real_frames_run_threshold") or {}
        rows.append([label, share, f"{first['false_success_before']['rate']:.2f}",
                     f"{sb.get('48', float('nan')):+.2f} / {sb.get('96', float('nan')):+.2f}",
                     f"{first['threshold']:.4f}", f"{calibration['missed_success']['rate']:.2f}",
                     f"{sa.get('48', float('nan')):+.2f}", _real_frames(both.get("before")),
                     _real_frames(both.get("after"))])
    return _table(["trained on", "replay share", "before: false success (whole replay)",
                   "before: separation by 48 / 96", "calibrated threshold", "calibration: successes missed",
                   "after: separation by 48", "real frames before: precision / recall / fires on failed",
                   "the same after"], rows)


SEPARATION = ("policy", "grpo_refresh_separation_small_h200")
# the runs of the separation-calibration test: (run, decoder, replay share of the detector's fine-tune)
SEPARATION_RUNS = (("refreshed_seed0", "full VAE decoder (bfloat16)", "0.5"),
                   ("realdet_refreshed_seed0", "full VAE decoder (bfloat16)", "0"),
                   ("light_refreshed_seed0", "light, 64 px", "0.5"))


def _rate(entry: dict) -> str:
    """A rate with its 95% interval and count: ``0.21 [0.10, 0.38] of 29``."""
    return f"{entry['rate']:.2f} [{entry['ci95'][0]:.2f}, {entry['ci95'][1]:.2f}] of {entry['of']}"


def grpo_refresh_separation() -> str:
    """The first refresh of Sword's seed 0 under the separation calibration, through the Wan decoder and the light
    decoder: the replay before the refresh (the pipeline's detector at 0.9; whole-replay agreement and false
    success, imagined success by 48 actions among real successes and real failures), the threshold the calibration
    set over the rollout horizon, and the refreshed detector on held-out replays at that threshold."""
    rows = []
    runs = _load(*SEPARATION, "grpo_refresh_summary.json")["runs"]
    for run_name, decoder, share in SEPARATION_RUNS:
        record = _load(*SEPARATION, run_name, "rl", "grpo", "refresh", "step_000000", "record.json")
        replay, detector = record["replay"], record["detector"]
        at48 = replay["imagined_success_by_horizon"]["48"]
        chosen = detector["candidates"][str(record["horizon"]["actions"])]
        rows.append([decoder, share, _rate(replay["agreement"]), _rate(replay["false_success"]),
                     f"{_rate(at48['real_success'])} / {_rate(at48['real_failure'])}",
                     f"{runs[run_name]['refreshes'][0]['separation_before']['48']:+.2f}",
                     f"{detector['threshold']:.4f}",
                     f"{_rate(chosen['real_success'])} / {_rate(chosen['real_failure'])}",
                     f"{record['trust']['separation']:+.2f}", _real_frames(detector.get("real_frames"))])
    return _table(["decoder", "replay share", "before: agreement (whole replay)", "before: false success (whole replay)",
                   "before: imagined success by 48 actions, real successes / real failures", "before: separation by 48",
                   "calibrated threshold", "after: imagined success by 48, real successes / real failures",
                   "after: separation by 48",
                   "real frames at the calibrated threshold: precision / recall / fires on failed"], rows)


PROBE = ("policy", "grpo_refresh_probe_small_4xh200")
PROBE_RUNS = (("refreshed_seed0", "Sword", "1"), ("g2_refreshed_seed0", "Sword", "2"),
              ("g3_refreshed_seed0", "Sword", "3"), ("ad_refreshed_seed0", "Sword, action dropout 0.1", "2"))


def grpo_refresh_probe() -> str:
    """The probe of a simulator's signal at GRPO step 0 (seed 0): the refresh's 64 real episodes, 8 starts rolled
    out 8 times each, replayed in the world model before it is refreshed. Per horizon, within the groups: the
    separation of real successes from real failures by the simulator's verdict, and the detector scores' AUC
    (0.5 = no ranking); then the share of groups the verdicts leave mixed at 48 actions (GRPO's horizon), and
    after the refresh the calibrated separation by 48 across episodes."""
    rows = []
    for run_name, world_model, guidance in PROBE_RUNS:
        record = _load(*PROBE, run_name, "rl", "grpo", "refresh", "step_000000", "record.json")
        replay, within = record["replay"], record["replay"]["within_group"]
        cells = [f"{within[h]['separation']:+.2f} / {within[h]['auc']:.2f}" for h in ("24", "48", "96", "all")]
        rows.append([world_model, guidance, f"{within['groups']} x {within['group_size']}",
                     f"{record['real_success']:.2f}", _rate(replay["false_success"]), *cells,
                     f"{within['48']['imagined_mixed']:.2f}", f"{record['trust']['separation']:+.2f}"])
    return _table(["world model", "action guidance", "groups", "real success", "before: false success (whole replay)",
                   "within groups by 24: separation / AUC", "by 48", "by 96", "whole replay",
                   "groups left mixed by 48", "after the refresh: separation by 48"], rows)


THREE_SEEDS = ("policy", "grpo_refresh_3seeds_small_4xh200")


def _imagined_success(run: str) -> list[float]:
    """A run's imagined success (the detector's verdict on its imagined rollouts) at every GRPO step."""
    with open(os.path.join(RESULTS_DIR, *THREE_SEEDS, run, "rl", "grpo", "train_history.jsonl")) as f:
        return [json.loads(line)["success_rate"] for line in f if line.strip()]


def grpo_refresh_three_seeds_diagnosis() -> str:
    """Per run of the three-seed refreshed comparison: the real gain, the imagined success over the first and
    the last 10 GRPO steps, and what every refresh's replay said of the simulator GRPO had trained in (its
    false successes on the policy's new real failures, its separation of real outcomes by 48 actions) and of
    the refreshed one, with the exploitation guard's rollbacks."""
    summary = _load(*THREE_SEEDS, "grpo_refresh_summary.json")
    rows = []

    def span(values: list[float], fmt: str = "{:.2f}") -> str:
        return f"{fmt.format(min(values))} to {fmt.format(max(values))}" if values else ""

    for name, run in summary["runs"].items():
        done = [r for r in run["refreshes"] if not r.get("skipped")]
        imagined = _imagined_success(name)[: run["steps"]]
        trips = [g for g in run.get("guard") or [] if g.get("trip")]
        s = run["sampled"]
        rows.append([_refresh_label(name), str(run["steps"]), f"{s['gain']:+.3f} [{s['ci95'][0]:+.3f}, {s['ci95'][1]:+.3f}]",
                     f"{statistics.mean(imagined[:10]):.2f} -> {statistics.mean(imagined[-10:]):.2f}" if imagined else "",
                     span([r["real_success"] for r in done]),
                     span([r["false_success_before"]["rate"] for r in done if r["false_success_before"]["rate"] is not None]),
                     span([r["separation_before"]["48"] for r in done if r["separation_before"].get("48") is not None],
                          "{:+.2f}"),
                     span([r["separation_after"]["48"] for r in done if r["separation_after"].get("48") is not None],
                          "{:+.2f}"),
                     ", ".join(f"{g['step']} (to {g['rolled_back_to']})" for g in trips) or "none"])
    return _table(["run", "GRPO steps", "sampled gain, 95% interval", "imagined success, first -> last 10 steps",
                   "refreshes: the policy's real success", "before each refresh: real failures imagined successes",
                   "before: separation by 48 actions", "after: separation by 48 actions",
                   "guard rollbacks at step (to step)"], rows)


SETTING_ARMS = ("policy", "grpo_env_setting_arms_mjx_2xh200")
SETTING_ARM_LABELS = {"A": "the learned simulator's: keyframes, 48 actions by 4, proprio missing",
                      "B": "keyframes, 48 actions by 4, true proprio", "C": "from rest, 220 actions, proprio missing"}
GROUND_TRUTH_SEEDS = ("policy", "grpo_mjx_seeds_small_4xh100")


def _step_gain(points: list[dict], step: int, policy: str) -> tuple[float, tuple[float, float]] | None:
    """The gain of ``policy`` (``greedy``: the point, else its entry) from step 0 to ``step`` and its 95% interval
    (paired where both points kept their outcomes); None where either point lacks it."""
    from sword_jax.rl.env_rollout import gain_interval

    at = {p["step"]: (p if policy == "greedy" else p.get(policy)) for p in points}
    a, b = at.get(0), at.get(step)
    if a is None or b is None:
        return None
    return b["mean"] - a["mean"], gain_interval(a, b)


def _gain_at(points: list[dict], step: int, policy: str) -> str:
    """:func:`_step_gain` as ``+0.068 [+0.006, +0.129]`` (empty where there is none)."""
    found = _step_gain(points, step, policy)
    if found is None:
        return ""
    gain, (lo, hi) = found
    return f"{gain:+.3f} [{lo:+.3f}, {hi:+.3f}]"


def _read_run(grpo: str) -> tuple[list[dict], list[dict]]:
    """``(success-curve points, train history)`` of the GRPO run at ``grpo``."""
    with open(os.path.join(grpo, "success_curve.json")) as f:
        points = json.load(f)["points"]
    with open(os.path.join(grpo, "train_history.jsonl")) as f:
        return points, [json.loads(line) for line in f if line.strip()]


def _seed_runs(folder: str) -> Iterator[tuple[str, list[dict], list[dict]]]:
    """``(seed dir, success-curve points, train history)`` of each ``s<k>`` under ``folder``, in name order: the
    ``grpo_env*`` run each one holds (``bench_policy grpo``'s layout)."""
    for seed_dir in sorted(d for d in os.listdir(folder) if re.fullmatch(r"s\d+", d)):
        here = os.path.join(folder, seed_dir)
        run = next(os.path.join(here, d) for d in sorted(os.listdir(here))
                   if d.startswith("grpo_env") and os.path.isdir(os.path.join(here, d)))
        yield seed_dir, *_read_run(run)


def grpo_setting_arms() -> str:
    """Ground-truth GRPO on MJX in the learned simulator's setting, one part at a time, per seed at step 20,
    beside the ground-truth recipe's runs (true proprio from rest) at the same step."""
    rows = []
    root = os.path.join(RESULTS_DIR, *SETTING_ARMS)
    for arm, label in SETTING_ARM_LABELS.items():
        for seed_dir, points, history in _seed_runs(os.path.join(root, arm)):
            last = points[-1]["step"]
            rollouts = [h["rollout_success"] for h in history]
            rows.append([label, seed_dir, str(last), _gain_at(points, last, "sampled"), _gain_at(points, last, "greedy"),
                         _gain_at(points, last, "sampled_proprio_masked") or "not run",
                         f"{statistics.median(h['mixed_fraction'] for h in history):.2f}",
                         f"{statistics.mean(rollouts[:5]):.2f} -> {statistics.mean(rollouts[-5:]):.2f}",
                         f"{statistics.mean(h['env_steps'] for h in history) / 1000:.0f} k"])
    for seed_dir in ("s0", "s1", "s2"):
        points = _load(*GROUND_TRUTH_SEEDS, seed_dir, "grpo_env_mjx", "success_curve.json")["points"]
        rows.append(["the ground-truth recipe: from rest, 220 actions, true proprio (4 x H100)", seed_dir, "20",
                     _gain_at(points, 20, "sampled"), _gain_at(points, 20, "greedy"), "not run", "", "", ""])
    return _table(["rollouts' setting", "seed", "GRPO steps", "sampled gain (true proprio), 95% interval",
                   "greedy gain", "sampled gain, proprio masked", "groups mixed (median)",
                   "training rollouts' success, steps 1-5 -> last 5", "env steps a GRPO step"], rows)


def _reward_source_rows(summary: dict, group_of: int | None = None, label: str | None = None) -> list[list[str]]:
    """The rows of :func:`_reward_source_table`: per arm and seed, the arm's label (or ``label``, the setting that
    tells apart several summaries' rows in one table), the gains sampled, sampled with proprio masked and greedy,
    what the training rollouts were paid, the groups they left mixed (with ``group_of``, as a count of that many
    groups), and for the world model paid by reality, the detector's verdicts on the same rollouts. Where any run
    was also evaluated as its GRPO executes the sampled policy (``sampled_as_trained``), that gain follows the
    sampled one (:func:`_reward_source_columns`)."""
    rows = []
    policies = ("sampled", *(("sampled_as_trained",) if _has_as_trained(summary) else ()), "sampled_proprio_masked",
                "greedy")
    for arm in ("gt", "exec", "det", "cal"):
        for _, run in sorted(summary["runs"].items()):
            if run["arm"] != arm:
                continue
            paid, det = run["paid_success"], run.get("detector")
            mixed = run["mixed_median"]
            rows.append([label or summary["arms"][arm]["label"], f"s{run['seed']}", str(run["steps"]),
                         *(f"{_pct(run[m]['gain'])} {_interval(run[m]['ci95'])}" if run.get(m) else "not run"
                           for m in policies),
                         f"{paid['first']:.3f} -> {paid['last']:.3f}",
                         f"{mixed * group_of:.0f} of {group_of}" if group_of else f"{mixed:.2f}",
                         _detector_cell(det)])
    return rows


REWARD_SOURCE_COLUMNS = ["GRPO's frames and reward", "seed", "steps", "sampled gain (points), 95% interval",
                         "sampled, proprio masked", "greedy", "its rollouts' paid success, steps 1-5 -> last 5",
                         "groups mixed (median)", "the detector on the same rollouts: success / agreement / precision"]


def _has_as_trained(summary: dict) -> bool:
    """Whether any run of a reward-source summary was evaluated as its GRPO executes the sampled policy."""
    return any(run.get("sampled_as_trained") for run in summary["runs"].values())


def _reward_source_columns(summary: dict) -> list[str]:
    """:data:`REWARD_SOURCE_COLUMNS`, with the sampled policy executed as GRPO executes it after the sampled gain
    where :func:`_has_as_trained`."""
    if not _has_as_trained(summary):
        return list(REWARD_SOURCE_COLUMNS)
    return [*REWARD_SOURCE_COLUMNS[:4], "sampled as trained (its rollouts' execution)", *REWARD_SOURCE_COLUMNS[4:]]


def _reward_source_table(summary: dict, group_of: int | None = None) -> str:
    """A reward-source summary (``bench_grpo_reward_source summary``) per arm and seed
    (:func:`_reward_source_rows`)."""
    return _table(_reward_source_columns(summary), _reward_source_rows(summary, group_of))


def grpo_reward_source() -> str:
    """The reward-source experiment per arm and seed (``policy_grpo_reward_source_small``,
    :func:`_reward_source_table`)."""
    return _reward_source_table(_load("latest.json")["policy_grpo_reward_source_small"])


# the reward-source experiment at 2 decisions of 8 actions from keyframes of every phase, in the 30,000-step world
# model of world_model_policy_split_30k_small_h200 (its bundle), 32 starts x 8, 3 seeds (2 x H200)
REWARD_SOURCE_BRANCHED = ("policy", "grpo_reward_source_branched_small_2xh200")


def grpo_reward_source_branched() -> str:
    """The reward-source experiment in short rollouts from every phase (``REWARD_SOURCE_BRANCHED``,
    :func:`_reward_source_table`), its groups counted of the step's 32."""
    return _reward_source_table(_load(*REWARD_SOURCE_BRANCHED, "grpo_reward_source.json"), group_of=32)


# the reward-source experiment at 6 decisions of 8 actions from keyframes of every phase, the ground-truth arm beside
# the world model paid by reality, the same world model's bundle, 64 starts x 8, 3 seeds (2 x H200)
REWARD_SOURCE_PHASES = ("policy", "grpo_reward_source_phases_h6_small_2xh200")


def grpo_reward_source_phases() -> str:
    """The reward-source experiment at 48 actions from every phase (``REWARD_SOURCE_PHASES``,
    :func:`_reward_source_table`), its groups counted of the step's 64."""
    return _reward_source_table(_load(*REWARD_SOURCE_PHASES, "grpo_reward_source.json"), group_of=64)


# ground-truth GRPO on MJX from keyframes of the first half of each demonstration at three decision lengths, the
# same demonstrations, 64 starts x 8, 3 seeds, one H200: {work dir in the record: the setting's row label}
FIRST_HALF_DECISIONS = ("policy", "grpo_first_half_decisions_small_h200")
FIRST_HALF_SETTINGS = {"h12x4": "12 decisions x 4 actions = 48", "h6x8": "6 decisions x 8 actions = 48",
                       "h4x8": "4 decisions x 8 actions = 32"}


def grpo_first_half_decisions() -> str:
    """Ground-truth GRPO from keyframes of the first half per decision length (``FIRST_HALF_DECISIONS``,
    :func:`_reward_source_rows` of each setting's summary), its groups counted of the step's 64."""
    rows = [row for folder, label in FIRST_HALF_SETTINGS.items()
            for row in _reward_source_rows(_load(*FIRST_HALF_DECISIONS, folder, "grpo_reward_source.json"), 64, label)]
    return _table(["rollouts from keyframes of the first half: decisions x actions", *REWARD_SOURCE_COLUMNS[1:-1]],
                  [row[:-1] for row in rows])


# ground-truth GRPO on MJX from keyframes of the first half at 12 decisions x 4 actions, evaluated also as it executes
# the sampled policy (4 actions of each chunk, proprio missing): {work dir in the record: the row label}, 64 x 8,
# 3 seeds, 40 steps, 2 x H200
FIRST_HALF_AS_TRAINED = ("policy", "grpo_first_half_as_trained_small_2xh200")
FIRST_HALF_AS_TRAINED_ARMS = {"centred": "centred", "std": "scaled by their std"}


def _gain_points(points: list[dict], step: int, policy: str) -> str:
    """:func:`_step_gain` in points, as ``+12.6 [+6.9, +18.1]`` (empty where there is none)."""
    found = _step_gain(points, step, policy)
    return "" if found is None else f"{_pct(found[0])} {_interval(found[1])}"


def _as_trained_span(points: list[dict], step: int) -> str:
    """The sampled policy's success executed as trained, from step 0 to ``step``, as ``0.356 -> 0.546`` (empty
    where either point lacks it)."""
    trained = {p["step"]: p["sampled_as_trained"]["mean"] for p in points if "sampled_as_trained" in p}
    return f"{trained[0]:.3f} -> {trained[step]:.3f}" if 0 in trained and step in trained else ""


def grpo_first_half_as_trained() -> str:
    """Ground-truth GRPO from keyframes of the first half, 12 x 4 actions (``FIRST_HALF_AS_TRAINED``), per advantage
    rule and seed: the gain of the sampled policy executed as GRPO executes it (4 actions of each sampled chunk,
    proprio missing) at steps 20 and 40 and its success from step 0 to the last; at the last step the gains of the
    sampled policy re-planning every action (true proprio, then proprio masked) and of the greedy ensembled one;
    and what the training rollouts were paid over the first and last 5 steps."""
    rows = []
    root = os.path.join(RESULTS_DIR, *FIRST_HALF_AS_TRAINED)
    for folder, label in FIRST_HALF_AS_TRAINED_ARMS.items():
        for seed_dir, points, history in _seed_runs(os.path.join(root, folder, "gt")):
            paid = [h["rollout_success"] for h in history]
            last = points[-1]["step"]
            rows.append([label, seed_dir, str(last), _gain_points(points, 20, "sampled_as_trained"),
                         _gain_points(points, last, "sampled_as_trained"), _as_trained_span(points, last),
                         *(_gain_points(points, last, m) for m in ("sampled", "sampled_proprio_masked", "greedy")),
                         f"{statistics.mean(paid[:5]):.3f} -> {statistics.mean(paid[-5:]):.3f}"])
    return _table(["advantages", "seed", "steps", "as trained: gain at step 20 (points), 95% interval",
                   "as trained: gain at the last step", "as trained: success, step 0 -> last",
                   "sampled, a new chunk every action: gain at the last step", "the same, proprio masked",
                   "greedy, ensembled", "its rollouts' paid success, steps 1-5 -> last 5"], rows)


# GRPO in Sword's world model in that setting (first-half keyframes, 12 x 4, 64 x 8, centred, seeds 0-2, 20 steps,
# 2 x H200): {run dir prefix in the record: the row label}; its summary (grpo_reward_source.json) holds the detector
FIRST_HALF_WORLD_MODEL = ("policy", "grpo_first_half_world_model_small_2xh200")
FIRST_HALF_WORLD_MODEL_ARMS = {"exec": "the world model's frames, paid by executing their actions on MJX",
                               "cal": "the same for 4 steps, then the detector at the threshold they set"}


def _first_half_row(label: str, seed_dir: str, points: list[dict], history: list[dict], step: int,
                    detector: dict | None) -> list[str]:
    """One row of :func:`grpo_first_half_world_model`: a run's figures at ``step`` from its curve and its history's
    first ``step`` steps (a ground-truth step's real outcome is ``rollout_success``, a world-model step's
    ``success_rate``, real where the step executed its actions: ``real_rollouts``)."""
    steps = [h for h in history if h["step"] <= step]
    real = [h for h in steps if "trajectories_sampled" in h or "real_rollouts" in h]
    used = sum(int(h.get("trajectories_sampled", h.get("real_rollouts", 0))) for h in steps)
    paid = statistics.mean(h.get("rollout_success", h.get("success_rate")) for h in real) if real else None
    cell = "" if paid is None else f"{paid:.3f}" + ("" if len(real) == len(steps) else f" (steps 1-{len(real)})")
    bounded = "" if not detector or detector.get("recall_bounded") is None else (
        f"; at its 5% bound: recall {detector['recall_bounded']:.2f}, precision {detector['precision_bounded']:.2f}")
    return [label, seed_dir, f"{used:,}", _gain_points(points, step, "sampled_as_trained"),
            _as_trained_span(points, step),
            _gain_points(points, step, "sampled"), _gain_points(points, step, "greedy"), cell,
            f"{statistics.median(h['mixed_groups'] for h in steps):.0f} of 64",
            (_detector_cell(detector) + bounded) if detector else ""]


def grpo_first_half_world_model(step: int = 20) -> str:
    """GRPO from keyframes of the first half, 12 x 4 actions, at ``step``: on real frames (the centred runs of
    ``FIRST_HALF_AS_TRAINED``) beside Sword's world model (``FIRST_HALF_WORLD_MODEL``), per arm and seed: the real
    episodes its steps consumed, the gain of the sampled policy executed as trained, re-planning every action and
    greedy, the real success of its training rollouts' actions, its groups with mixed outcomes, and the detector on
    the world model's executed rollouts."""
    rows = []
    for seed_dir, points, history in _seed_runs(os.path.join(RESULTS_DIR, *FIRST_HALF_AS_TRAINED, "centred", "gt")):
        rows.append(_first_half_row("real frames, paid by MJX (ground truth)", seed_dir, points, history, step, None))
    root = os.path.join(RESULTS_DIR, *FIRST_HALF_WORLD_MODEL)
    runs = _load(*FIRST_HALF_WORLD_MODEL, "grpo_reward_source.json")["runs"]
    for arm, label in FIRST_HALF_WORLD_MODEL_ARMS.items():
        for name in sorted(n for n in runs if runs[n]["arm"] == arm):
            points, history = _read_run(os.path.join(root, name, "rl", "grpo"))
            rows.append(_first_half_row(label, f"s{runs[name]['seed']}", points, history, step,
                                        runs[name].get("detector")))
    return _table(["GRPO's frames and reward", "seed", f"real episodes by step {step}",
                   f"as trained: gain at step {step} (points), 95% interval", f"as trained: success, step 0 -> {step}",
                   "sampled, a new chunk every action: gain", "greedy, ensembled: gain",
                   "real success of its training rollouts' actions", "groups mixed a step (median)",
                   "the detector on its executed rollouts: success / agreement / precision; AUC; at the threshold "
                   "that bounds its false success at 5%"], rows)


# where the world model's closed loop keeps reality's payment, by the start's step in its demonstration: gt beside
# exec, 12 x 4 from keyframes of every phase, 64 x 8, seeds 0-1, 4 steps, 1 x H200 (grpo_reward_source.json's by_start)
BY_START = ("policy", "grpo_by_start_small_h200")
# the same world model from the second half of each demonstration only (keyframe_from 0.5), exec alone, step 1
BY_START_WINDOW = ("policy", "grpo_by_start_window_small_h200")
# gt beside rexec: the same world model refreshed once at step 0 on 128 MJX episodes of the policy, as BY_START
BY_START_REFRESH = ("policy", "grpo_by_start_refresh_small_h200")
# gt beside rexec refreshed once at step 0 on 128 MJX episodes and on its own closed loop (512 trajectories from 64
# keyframe starts, their actions executed on MJX), 2,000 fine-tune steps at 1e-4, as BY_START
BY_START_CLOSED_LOOP = ("policy", "grpo_by_start_closed_loop_small_h200")


def _by_start_pooled(bins: list[dict], above: int = 48) -> list[dict]:
    """A run's ``by_start`` bins with those from ``above`` actions on pooled into one (the last, ``from_step`` =
    ``above``, ``to_step`` None); the others keep their upper edge as ``to_step``."""
    out = []
    for b, nxt in zip(bins, [*bins[1:], None]):
        if b["from_step"] >= above:
            break
        out.append({**b, "to_step": nxt["from_step"] if nxt else None})
    late = [b for b in bins if b["from_step"] >= above]
    if late:
        keys = ("rollouts", "real", "said", "said_real")
        out.append({"from_step": above, "to_step": None,
                    **{k: sum(b[k] for b in late) for k in keys if k in late[0]}})
    return out


# the world-model arms a by-start record may hold, as its table names them (a record of RECORD_ARMS names its own)
BY_START_ARMS = {"exec": "as trained", "rexec": "refreshed"}
RECORD_ARMS = {BY_START_CLOSED_LOOP: {"rexec": "refreshed on its closed loop"}}


def grpo_by_start(*records: tuple[str, ...]) -> str:
    """Per bin of the start's step, seed and world-model arm of each of ``records`` (default :data:`BY_START`; its
    ``grpo_reward_source.json``'s ``by_start``, :data:`BY_START_ARMS`): ground truth's rollouts and real success
    (the same record's ``gt`` run of that seed; blank without one) beside the world model's rollouts paid by
    executing their actions, the share of ground truth's real success they kept, and what the detector said of
    them: its success and its precision (the share of its verdicts of success that reality paid)."""
    rows = []
    for record in records or (BY_START,):
        rows += _by_start_rows(_load(*record, "grpo_reward_source.json")["runs"],
                               RECORD_ARMS.get(tuple(record), BY_START_ARMS))
    rows.sort(key=_bin_and_seed)  # stable: the records' order kept
    return _table(["start's step in its demonstration (actions)", "seed", "world model", "ground truth: rollouts",
                   "ground truth: real success", "world model, paid by execution: rollouts", "its real success",
                   "kept (world model over ground truth)", "the detector's success on its rollouts",
                   "the detector's precision"], rows)


def _by_start_rows(runs: dict, arms: dict[str, str] = BY_START_ARMS) -> list[list[str]]:
    """:func:`grpo_by_start`'s rows of one record's ``runs``, its world-model arms named by ``arms``."""
    def bins(arm: str, seed: int) -> list[dict] | None:
        found = [r for r in runs.values() if r["arm"] == arm and r["seed"] == seed and r.get("by_start")]
        return _by_start_pooled(found[0]["by_start"]) if found else None

    rows = []
    for seed in sorted({r["seed"] for r in runs.values()}):
        truth = {b["from_step"]: b for b in bins("gt", seed) or []}
        for arm, label in arms.items():
            for e in bins(arm, seed) or []:
                g = truth.get(e["from_step"])
                if not e["rollouts"] or (truth and not (g and g["rollouts"])):
                    continue
                paid_e = e["real"] / e["rollouts"]
                paid_g = g["real"] / g["rollouts"] if g else None
                rows.append([_bin_span(e), f"s{seed}", label, f"{g['rollouts']:,}" if g else "",
                             f"{paid_g:.3f}" if g else "", f"{e['rollouts']:,}", f"{paid_e:.3f}",
                             f"{100 * paid_e / paid_g:.0f}%" if paid_g else "", f"{e['said'] / e['rollouts']:.2f}",
                             f"{e['said_real'] / e['said']:.2f}" if e["said"] else ""])
    return rows


def _grpo_runs(record: tuple[str, ...], arm: str) -> Iterator[tuple[int, str]]:
    """``(seed, its rl/grpo folder)`` of each of ``record``'s ``<arm>_s<seed>`` runs (seeds 0-2, those present)."""
    for seed in (0, 1, 2):
        run = os.path.join(RESULTS_DIR, *record, f"{arm}_s{seed}", "rl", "grpo")
        if os.path.isdir(run):
            yield seed, run


def _closed_loop_decisions(history: list[dict]) -> list[int]:
    """The decisions at which a run's history records its closed loop (``closed_loop_frame_error_<k>``), ascending."""
    return sorted(int(k.rsplit("_", 1)[1]) for k in history[0] if re.fullmatch(r"closed_loop_frame_error_\d+", k))


def grpo_refresh_fidelity(records: Sequence[tuple[tuple[str, ...], str, str]] = (
        (BY_START, "exec", "as trained"), (BY_START_REFRESH, "rexec", "refreshed"))) -> str:
    """Per seed, the world model as trained (:data:`BY_START`'s ``exec`` runs) and refreshed (:data:`BY_START_REFRESH`'s
    ``rexec``), means over their GRPO steps: what reality paid their rollouts' actions, and where their closed loop
    left the real one at its first and last decision (frame error and the policy's greedy action gap to the real
    frame, with the VAE alone's at the last); for a refreshed run, what its refresh fine-tuned on and its last loss."""
    rows = []
    for record, arm, label in records:
        for seed, run in _grpo_runs(record, arm):
            history = _history_rows(os.path.join(run, "train_history.jsonl"))
            last = _closed_loop_decisions(history)[-1]

            def mean(key: str) -> str:
                return f"{statistics.mean(h[key] for h in history):.3f}"

            refresh = ""
            if os.path.exists(os.path.join(run, "refreshes.json")):
                with open(os.path.join(run, "refreshes.json")) as f:
                    made = json.load(f)[0]
                wm, loop = made["world_model"], made.get("closed_loop")
                refresh = (f"{wm['real_episodes']} real episodes + {wm['training_episodes']} training"
                           + (f" + its closed loop ({loop['episodes']} trajectories, {loop['share']:.0%} of each batch)"
                              if loop and "episodes" in loop else "")
                           + f", {wm['steps']:,} steps, loss {wm['last']['loss']:.3f}")
            rows.append([f"s{seed}", label, str(len(history)), mean("success_rate"),
                         f"{mean('closed_loop_frame_error_1')} / {mean(f'closed_loop_frame_error_{last}')}",
                         mean(f"closed_loop_frame_error_vae_{last}"),
                         f"{mean('closed_loop_action_gap_1')} / {mean(f'closed_loop_action_gap_{last}')}",
                         mean(f"closed_loop_action_gap_vae_{last}"), refresh])
    rows.sort(key=lambda r: r[0])  # stable: as trained before refreshed
    return _table(["seed", "world model", "steps", "real success of its rollouts' actions",
                   "frame error to the real frame, first / last decision", "the VAE alone, last",
                   "greedy action gap, first / last decision", "the VAE alone, last", "its refresh"], rows)


CLOSED_LOOP_RUNS = ((BY_START, "exec", "as trained"), (BY_START_REFRESH, "rexec", "refreshed"),
                    (BY_START_CLOSED_LOOP, "rexec", "refreshed on its closed loop"))


def grpo_closed_loop_decisions(records: Sequence[tuple[tuple[str, ...], str, str]] = CLOSED_LOOP_RUNS) -> str:
    """Per decision of the imagined rollouts, each record's arm (``(record, arm, label)``, seeds 0-2 where present):
    the frame error to the real frame and the policy's greedy action gap to its actions on the real frame, means over
    the run's GRPO steps, as ``s0 / s1`` cells (:func:`sword_jax.rl.imagined_check.closed_loop_fidelity`)."""
    cells: dict[str, dict[int, list[str]]] = {}
    decisions = 0
    for record, arm, label in records:
        for what in ("frame_error", "action_gap"):
            cells.setdefault(f"{what}:{label}", {})
        for _, run in _grpo_runs(record, arm):
            history = _history_rows(os.path.join(run, "train_history.jsonl"))
            last = _closed_loop_decisions(history)[-1]
            decisions = max(decisions, last)
            for what in ("frame_error", "action_gap"):
                for d in range(1, last + 1):
                    mean = statistics.mean(h[f"closed_loop_{what}_{d}"] for h in history)
                    cells[f"{what}:{label}"].setdefault(d, []).append(f"{mean:.3f}")
    labels = [label for _, _, label in records]
    columns = [f"{what}:{label}" for what in ("frame_error", "action_gap") for label in labels]
    rows = [[str(d), *(" / ".join(cells[c].get(d, [])) for c in columns)] for d in range(1, decisions + 1)]
    names = {"frame_error": "frame error", "action_gap": "greedy action gap"}
    return _table(["decision", *(f"{names[c.split(':')[0]]}, {c.split(':', 1)[1]} (s0 / s1)" for c in columns)],
                  rows)


def grpo_closed_loop_fit(record: tuple[str, ...] = BY_START_CLOSED_LOOP) -> str:
    """Per seed, a refresh on the world model's own closed loop (``record``'s ``rexec`` runs, their step-0 refresh):
    how far its closed loop had drifted from the real latents of the same actions after decisions 1, 2, 6 and 12
    (mean squared difference, :func:`sword_jax.rl.closed_loop.drift_by_decision`), and on held-out trajectories'
    segments the sample error (relative squared error, the inference sampler) before and after the fine-tune: from
    the real start's context (decision 1), from its own closed loop's (decisions 2-11), and on its training
    segments."""
    rows = []
    for seed, run in _grpo_runs(record, "rexec"):
        with open(os.path.join(run, "refreshes.json")) as f:
            loop = json.load(f)[0]["closed_loop"]
        drift, fit = loop["latent_drift_by_decision"], loop["fit"]

        def change(part: str) -> str:
            before, after = fit["before"][part], fit["after"][part]
            if not before:
                return ""
            b, a = before["sample_error"], after["sample_error"]
            return f"{b:.4f} -> {a:.4f} ({100 * (a - b) / b:+.0f}%)"

        rows.append([f"s{seed}", f"{loop['episodes']} ({loop['starts']} starts x {loop['group_size']})",
                     f"{loop['real_success']:.3f}", " / ".join(f"{drift[d - 1]:.3f}" for d in (1, 2, 6, 12)),
                     f"{fit['held_out_trajectories']}", change("first_decision"), change("closed_loop"),
                     change("training")])
    return _table(["seed", "closed-loop trajectories executed", "their real success",
                   "latent drift after decision 1 / 2 / 6 / 12", "held-out trajectories",
                   "sample error from the real start's context (decision 1)",
                   "sample error from its own closed loop's context (decisions 2-11)",
                   "sample error on its training segments"], rows)


# the cost of a frame a decision late by the start's step: ground-truth GRPO's keyframe starts of steps 1-4 at seeds
# 0-1 (the by-start record's draws), the supervised policy on real and on late frames (C engine, 2-core CPU)
LAG_BY_START = ("policy", "lag_by_start_small_cpu")


def _lag_runs(record: tuple[str, ...], folder: str) -> Iterator[tuple[int, dict]]:
    """``(seed, lag_by_start)`` of each seed's ``<folder><seed>/action_gap.json`` under ``record`` (seeds 0-2,
    those present)."""
    for seed in (0, 1, 2):
        path = os.path.join(RESULTS_DIR, *record, f"{folder}{seed}", "action_gap.json")
        if os.path.exists(path):
            with open(path) as f:
                yield seed, json.load(f)["lag_by_start"]


def _bin_span(b: dict) -> str:
    """A pooled by-start bin's span of start steps: ``a-b`` or, the last, ``a+``."""
    return f"{b['from_step']}-{b['to_step'] - 1}" if b["to_step"] is not None else f"{b['from_step']}+"


def _bin_and_seed(row: list[str]) -> tuple[int, str]:
    """The sort key of a by-start table's row: its bin's first start step (cell 0, :func:`_bin_span`), its seed
    (cell 1)."""
    return int(row[0].rstrip("+").split("-")[0]), row[1]


def lag_by_start_table(record: tuple[str, ...] = LAG_BY_START, world_model: tuple[str, ...] = BY_START) -> str:
    """Per bin of the start's step and seed: the real success of the rollouts on real frames and on frames a
    decision late (``record``'s ``s<seed>/action_gap.json``, ``lag_by_start``), the share the late frames kept, and
    beside it the share the world model's frames kept in ``world_model``'s by-start record (its ``exec`` over its
    ``gt``, the same seed)."""
    # (bin, seed) -> the world model's kept share: grpo-by-start's cell of its runs as trained
    kept = {(r[0], r[1]): r[7] for r in _by_start_rows(_load(*world_model, "grpo_reward_source.json")["runs"])
            if r[2] == BY_START_ARMS["exec"]}
    rows = []
    for seed, lag in _lag_runs(record, "s"):
        for real, late in zip(_by_start_pooled(lag["real"]), _by_start_pooled(lag["lag_1"])):
            if not real["rollouts"]:
                continue
            paid, late_paid = real["real"] / real["rollouts"], late["real"] / late["rollouts"]
            span = _bin_span(real)
            rows.append([span, f"s{seed}", f"{real['rollouts']:,}", f"{paid:.3f}", f"{late_paid:.3f}",
                         f"{100 * late_paid / paid:.0f}%" if paid else "", kept.get((span, f"s{seed}"), "")])
    rows.sort(key=_bin_and_seed)
    return _table(["start's step in its demonstration (actions)", "seed", "rollouts", "real success, real frames",
                   "the frame a decision late", "kept (late over real)",
                   "kept by the world model's frames (table `grpo-by-start`)"], rows)


def lag_by_start_actions(record: tuple[str, ...] = LAG_BY_START) -> str:
    """Per bin of the start's step and seed (``record``'s ``late_actions_s<seed>/action_gap.json``, runs of
    ``bench_action_gap --lag-late-actions``): the real success of the rollouts on real frames and the share of it
    kept when the policy reads, at each decision, the frame some actions before the decision's end (each of the
    run's ``late_actions``, then a whole decision, ``lag_1``)."""
    rows, header = [], None
    for seed, lag in _lag_runs(record, "late_actions_s"):
        late = [f"{j} action{'s' if j > 1 else ''} late" for j in lag["late_actions"]]
        if header not in (None, late):
            raise ValueError(f"lag-by-start-actions: the runs of {record} read different lags ({header} and {late})")
        header = late
        names = [f"late_{j}_actions" for j in lag["late_actions"]] + ["lag_1"]
        pooled = {name: _by_start_pooled(lag[name]) for name in ["real", *names]}
        for i, real in enumerate(pooled["real"]):
            if not real["rollouts"]:
                continue
            paid = real["real"] / real["rollouts"]
            rows.append([_bin_span(real), f"s{seed}", f"{real['rollouts']:,}", f"{paid:.3f}"] + [
                f"{pooled[n][i]['real'] / pooled[n][i]['rollouts']:.3f} "
                f"({100 * pooled[n][i]['real'] / real['real']:.0f}%)" if real["real"] else "" for n in names])
    rows.sort(key=_bin_and_seed)
    return _table(["start's step in its demonstration (actions)", "seed", "rollouts", "real success, real frames",
                   *[f"{h} (kept)" for h in header or []], "a decision late (kept)"], rows)


def _view_cells(name: str, v: dict, real: dict) -> list[str]:
    """A view probe's success with its interval, and its difference from the ``real`` view with the 95% interval
    of that difference (empty for the real view itself)."""
    from sword_jax.rl.env_rollout import difference_interval

    lo, hi = difference_interval(v["successes"], v["episodes"], real["successes"], real["episodes"])
    return [_ci(v),
            "" if name == "real" else f"{_pct(v['mean'] - real['mean'])} [{-100 * hi:+.1f}, {-100 * lo:+.1f}]"]


def policy_view() -> str:
    """The policy's real success on MJX per view of its frames (``benchmarks.bench_policy_view``), with the
    difference from the real view and its 95% interval."""
    views = _load("policy", "policy_view_small_4xh200", "view_results.json")["views"]
    rows = []
    for name, v in views.items():
        (blur, gain, noise) = (v["parameters"][k] for k in ("blur_sigma_px", "gain", "noise_std"))
        rows.append([name, f"{blur:g}", f"{gain:g}", f"{noise:g}", *_view_cells(name, v, views["real"])])
    return _table(["view", "blur sigma (px of 128)", "brightness gain", "noise std (of 255)",
                   "success, 500 episodes (95% interval)", "against the real view, points (95% interval)"], rows)


def closed_loop() -> str:
    """Where the closed loop through the world model breaks, per length of its training
    (``bench_grpo_reward_source closed-loop``): what reality paid the imagined actions and how far the frames the
    policy read, and its greedy actions on them, were from the real ones at the first and last decision."""
    runs = _load("policy", "closed_loop_small_h200", "closed_loop.json")["runs"]
    rows = [[f"{r['world_model_steps']:,}", f"{r['world_model_loss']:.3f}", *_closed_loop_cells(r)] for r in runs.values()]
    return _table(["world model steps", "its loss (last 10 logged)", *CLOSED_LOOP_COLUMNS], rows)


# a closed-loop run's columns (bench_grpo_reward_source closed-loop): its steps, what reality paid, the detector,
# and the first and last decisions' frame error and greedy action gap
CLOSED_LOOP_COLUMNS = ("GRPO steps", "real success of the imagined actions (95% interval)", "the detector said",
                       "frame error, decision 1 -> 11", "greedy action gap, decision 1 -> 11")


def _closed_loop_cells(r: dict) -> list[str]:
    """:data:`CLOSED_LOOP_COLUMNS` of one run of a ``closed_loop.json``."""
    return [str(r["steps"]), _paid(r["paid_success"]),
            f"{r['detector_success']:.3f}", f"{r['frame_error_first']:.3f} -> {r['frame_error_last']:.3f}",
            f"{r['action_gap_first']:.3f} -> {r['action_gap_last']:.3f}"]


def _paid(paid: dict) -> str:
    """What reality paid a closed-loop run's trajectories: ``rate [low, high] of N``."""
    return f"{paid['rate']:.3f} [{paid['ci95'][0]:.3f}, {paid['ci95'][1]:.3f}] of {paid['of']:,}"


CLOSED_LOOP_VAE = ("policy", "closed_loop_vae_small_h200")


def closed_loop_sampler() -> str:
    """The closed loop through one world model (12,000 steps) at two Euler step counts per chunk
    (``bench_grpo_reward_source closed-loop``): what reality paid the imagined actions and the first and last
    decisions' frame error and greedy action gap."""
    runs = _load(*CLOSED_LOOP_VAE, "closed_loop.json")["runs"]
    return _table(["sampler", *CLOSED_LOOP_COLUMNS], [[label, *_closed_loop_cells(r)] for label, r in runs.items()])


def closed_loop_prev() -> str:
    """Per decision of the closed loop (the 5-Euler-step run, means over its steps): the frame the policy read
    and its greedy actions on it against the real frame its actions reached and against the real frame one
    decision earlier, and the real motion over the decision."""
    run = _load(*CLOSED_LOOP_VAE, "closed_loop.json")["runs"]["5 Euler steps"]
    d = run["per_decision"]
    rows = [[str(k), f"{d['frame_error'][i]:.3f}", f"{d['frame_error_prev'][i]:.3f}", f"{d['motion'][i]:.3f}",
             f"{d['action_gap'][i]:.3f}", f"{d['action_gap_prev'][i]:.3f}"] for i, k in enumerate(d["decisions"])]
    return _table(["decision", "frame error to the real frame", "to the real frame a decision earlier",
                   "real motion over the decision", "greedy action gap to the real frame",
                   "to the real frame a decision earlier"], rows)


def policy_view_vae() -> str:
    """The policy's real success on MJX reading the real frames, the frame of the decision before, and the real
    frames round-tripped through the pipeline's VAE (``bench_policy_view --views real,lag_1,vae``)."""
    data = _load(*CLOSED_LOOP_VAE, "view_vae", "view_results.json")
    views, labels = data["views"], {"real": "the real frame", "lag_1": "the real frame of the decision before",
                                    "vae": "the real frame round-tripped through the VAE (1,000 steps)"}
    real = views["real"]
    rows = [[labels.get(name, name), *_view_cells(name, v, real)] for name, v in views.items()]
    return _table(["what the policy reads at each decision", f"real success, {real['episodes']} episodes (95% interval)",
                   "against the real frame, points (95% interval)"], rows)


def action_gap() -> str:
    """How far each view moves the policy's greedy actions and frames, and one decision of real motion
    (``benchmarks.bench_action_gap``): the scale of the closed loop's figures."""
    data = _load("policy", "action_gap_small_cpu", "action_gap.json")
    rows = [[name, _ci(v["action_gap"]),
             f"{v['frame_error']['mean']:.3f}"] for name, v in data["views"].items()]
    step = data["consecutive_decisions"]
    rows.append(["the real frame one decision later", _ci(step["action_gap"]), f"{step['frame_error']['mean']:.3f}"])
    return _table(["the frame the policy reads", f"greedy action gap to the real frame ({data['frames']} frames, 95% "
                   "interval)", "frame error"], rows)


def lag_success() -> str:
    """The policy's real success reading the real frames and reading each decision the frame of the decision
    before (``bench_action_gap --lag-episodes-per-task``)."""
    lag = _load("policy", "action_gap_small_cpu", "action_gap.json")["lag"]
    rows = [[label, _ci(lag[k]),
             "" if k == "real" else f"{_pct(lag['difference']['mean'])} {_interval(lag['difference']['ci95'])}"]
            for k, label in (("real", "the real frame"), ("lag_1", "the frame of the decision before"))]
    return _table(["what the policy reads at each decision", f"real success, {lag['real']['episodes']} episodes "
                   "(95% interval)", "difference, points"], rows)


def lag_proprio() -> str:
    """The lag's cost in real success per proprio input (``bench_action_gap --lag-proprio``): whether a policy
    that reads the arm's state still needs the current frame."""
    data = _load("policy", "lag_proprio_small_cpu", "action_gap.json")["lag_by_proprio"]
    labels = {"missing": "missing (GRPO in the world model's mode)", "true": "the environment's",
              "reckoned": "dead-reckoned from the actions (what the world model can report)"}
    rows = [[labels[mode], _ci(lag["real"]), _ci(lag["lag_1"]),
             f"{_pct(lag['difference']['mean'])} {_interval(lag['difference']['ci95'])}"] for mode, lag in data.items()]
    episodes = next(iter(data.values()))["real"]["episodes"]
    return _table(["proprio the policy reads", f"real frames, {episodes} episodes (95% interval)",
                   "the frame of the decision before", "difference, points"], rows)


SIM_FIDELITY = ("policy", "sim_fidelity_small_4xh200")
SIM_FIDELITY_LABELS = {"base": "base: 16x spatial, 8 x 8 latents", "vae8x": "8x spatial, 16 x 16 latents",
                       "lpips": "base with LPIPS beside the pixel loss"}


def sim_fidelity() -> str:
    """Per VAE variant and for the decoder-aware policy (``bench_sim_fidelity``): the policy's MJX success on
    real and on VAE-round-tripped frames, and what reality paid its actions chosen in that variant's world model,
    with the first decision's frame error and greedy action gap beside the VAE alone's."""
    summary = _load(*SIM_FIDELITY, "summary.json")
    rows = [(SIM_FIDELITY_LABELS.get(v, v), "policy_d50", e, e) for v, e in summary["variants"].items()]
    for kind, label in (("decoded", "policy_d50 fine-tuned on half decoded frames"),
                        ("imagined", "policy_d50 fine-tuned on half imagined frames"),
                        ("control", "policy_d50 fine-tuned alike on real frames")):
        if kind in summary:  # in its variant's VAE and world model
            variant = summary[kind]["variant"]
            rows.append((SIM_FIDELITY_LABELS[variant], label, summary[kind], summary["variants"][variant]))
    out = []
    for vae, policy, e, pipe in rows:
        view, ex = e["view"], e["exec"]
        d = view["difference"]
        out.append([vae, policy, f"{pipe['world_model']['loss']:.3f}", _ci(view["real"]), _ci(view["vae"]),
                    f"{_pct(d['value'])} {_interval(d['ci95'])}",
                    f"{view['round_trip_levels']['mean_abs_error']['all']:.1f}",
                    _paid(ex["paid_success"]),
                    f"{ex['frame_error_first']:.3f} ({ex['frame_error_vae_first']:.3f})",
                    f"{ex['action_gap_first']:.3f} ({ex['action_gap_vae_first']:.3f})",
                    f"{ex['frame_error_last']:.3f} / {ex['action_gap_last']:.3f}"])
    episodes = next(iter(summary["variants"].values()))["view"]["real"]["episodes"]
    return _table(["VAE", "policy", "world model loss", f"real frames, {episodes} episodes (95% interval)",
                   "frames through the VAE", "difference, points", "round trip error (of 255)",
                   "real success of the actions chosen in the world model", "frame error at decision 1 (VAE alone)",
                   "greedy action gap at decision 1 (VAE alone)", "decision 11: frame error / action gap"], out)


SIM_FIDELITY_IMAGINED = ("policy", "sim_fidelity_imagined_small_h200")
# kind -> (its SFT folder, the suffix of its runs): bench_sim_fidelity.FINE_TUNES, not imported (it loads jax)
SIM_FIDELITY_TUNES = {"imagined": ("policy_img", "img"), "control": ("policy_ctl", "ctl"),
                      "decoded": ("policy_dec", "dec")}


def _fine_tune_frames(sft_results: dict) -> tuple[str, str]:
    """A fine-tune's frames (where its decoded share came from, the replay's window) and its last training batch's
    loss beside the held-out demonstrations' (real frames, teacher-forced) and their action L1."""
    rl, last = sft_results["rl"], sft_results["runs"][0]["history"][-1]
    sft, per_decision = rl["sft"], rl["imagined"]["execute_steps"] or rl["chunk_len"]
    window = sft["decoded_window"] or rl["imagined"]["max_chunks"] * per_decision
    source = {"world_model": f"imagined by the world model in windows of {window} actions, {per_decision} a decision",
              "vae": "through the VAE's video round trip"}[sft["decoded_source"]]
    frames = f"{sft['decoded_fraction']:.0%} {source}, the rest real" if sft["decoded_fraction"] else "real only"
    return frames, f"{last['loss']:.3f} / {last['heldout_loss']:.3f} ({last['heldout_action_l1']:.4f})"


def sim_fidelity_fine_tunes(parts: tuple[str, ...] = SIM_FIDELITY_IMAGINED) -> str:
    """The fine-tunes of a ``bench_sim_fidelity`` run beside the policy they start from (``summary.json`` and each
    fine-tune's ``sft_results.json``): the frames each trained on, its last training batch's loss and the held-out
    demonstrations' (real frames, teacher-forced), its own SFT evaluation, the view probe, and what reality paid its
    actions chosen in the world model, or what stopped that run."""
    summary = _load(*parts, "summary.json")
    stopped = _load(*parts, "sim_fidelity_summary.json").get("stopped_at_deadline", [])
    variant = next(iter(summary["variants"]))
    rows = [("policy_d50", "(the policy the fine-tunes start from)", "-", summary["variants"][variant],
             f"exec_{variant}")]
    for kind, (folder, suffix) in SIM_FIDELITY_TUNES.items():
        if kind in summary:
            tuned = summary[kind]
            rows.append((f"policy_d50 fine-tuned ({kind})", *_fine_tune_frames(_load(*parts, folder, "sft_results.json")),
                         tuned, f"exec_{tuned['variant']}_{suffix}"))
    out = []
    for policy, frames, losses, e, exec_job in rows:
        view, d = e["view"], e["view"]["difference"]
        paid = _paid(e["exec"]["paid_success"]) if "exec" in e else "not measured: " + (
            "the run's deadline stopped it before its step" if exec_job in stopped else e["missing"]["exec"])
        out.append([policy, frames, losses, _ci(e["sft"]) if "sft" in e else "-", _ci(view["real"]),
                    _ci(view["vae"]), f"{_pct(d['value'])} {_interval(d['ci95'])}", paid])
    episodes = rows[0][3]["view"]["real"]["episodes"]
    sft_episodes = next(e["sft"]["episodes"] for *_, e, _ in rows[1:] if e.get("sft"))
    return _table(["policy", "frames it was fine-tuned on", "loss: last batch / held-out real (action L1)",
                   f"greedy with ensembling, {sft_episodes} MJX episodes", f"real frames, {episodes} episodes, T 0.5",
                   "frames through the VAE", "difference, points", "real success of the actions chosen in the "
                   "world model"], out)


SIM_FIDELITY_STEPS = ("policy", "sim_fidelity_world_model_steps_small_h200")


def sim_fidelity_world_model_steps(parts: tuple[str, ...] = SIM_FIDELITY_STEPS) -> str:
    """The ``exec`` runs of a ``bench_sim_fidelity --exec-checkpoints`` run, one per world-model checkpoint and
    sampler (``summary.json``): the world model's loss to that step, what reality paid the imagined actions, what
    the detector said, and the first and last decisions' frame error and greedy action gap beside the VAE alone's;
    runs the deadline left unstarted are named (``sim_fidelity_summary.json``)."""
    summary = _load(*parts, "summary.json")
    not_started = _load(*parts, "sim_fidelity_summary.json").get("not_started", [])
    out = []
    for variant, entry in summary["variants"].items():
        runs = entry.get("checkpoints", {})
        for name, run in runs.items():
            ex, sampler = run["exec"], str(run["sample_steps"] or "5 (the config's)")
            if isinstance(ex, str):
                out.append([f"{run['step']:,}", "-", sampler, f"not measured: {ex}", "", "", ""])
                continue
            out.append([f"{run['step']:,}", f"{ex['world_model_loss']:.3f}", sampler, _paid(ex["paid_success"]),
                        f"{ex['detector_success']:.3f}",
                        f"{ex['frame_error_first']:.3f} -> {ex['frame_error_last']:.3f} ({ex['frame_error_vae_first']:.3f})",
                        f"{ex['action_gap_first']:.3f} -> {ex['action_gap_last']:.3f} ({ex['action_gap_vae_first']:.3f})"])
        for name in (n for n in not_started if n.startswith(f"exec_{variant}_at") and n not in runs):
            step, _, sampler = name[len(f"exec_{variant}_at"):].partition("_s")
            out.append([f"{int(step):,}", "-", sampler or "5 (the config's)",
                        "not measured: the run's deadline came before it started", "", "", ""])
    return _table(["world model steps", "its loss (last 10 logged to there)", "flow sampler steps",
                   "real success of the imagined actions (95% interval)", "the detector said",
                   "frame error, decision 1 -> 11 (the VAE alone at 1)",
                   "greedy action gap, decision 1 -> 11 (the VAE alone at 1)"], out)


def _false_successes(row: dict) -> tuple[int, int]:
    """A ``closed_loop.json`` row's real failures that the detector called successes, and its real failures."""
    true = row["precision"]["successes"] if row["precision"] else 0
    return row["detector"]["successes"] - true, row["paid"]["of"] - row["paid"]["successes"]


CLOSED_LOOP_NOISE = ("policy", "closed_loop_noise_small_h200")


def closed_loop_noise(record: tuple[str, ...] = CLOSED_LOOP_NOISE, decisions: tuple[int, ...] = (1, 6, 11)) -> str:
    """``bench_closed_loop``'s variants of one world model (its ``closed_loop.json``): per setting what reality paid
    the imagined actions, what the detector said and the share of the real failures it called successes, the frame
    error and greedy action gap at ``decisions``, and the difference of what reality paid against the first
    setting, paired; then the same policy on MJX's own frames."""
    out = _load(*record, "closed_loop.json")
    rows = []
    for v in out["variants"]:
        by = {d["decision"]: d for d in v["decisions"]}
        false, failures = _false_successes(v)
        vs = v.get("vs_first")
        rows.append([", ".join(v["overrides"]), _paid(v["paid"]), f"{v['detector']['rate']:.3f}",
                     f"{false / failures:.3f} ({false} of {failures})",
                     " / ".join(f"{by[k]['frame_error']:.3f}" for k in decisions),
                     " / ".join(f"{by[k]['action_gap']:.3f}" for k in decisions),
                     f"{_pct(vs['difference'])} {_interval(vs['ci95'])}" if vs else "-"])
    rows.append(["the policy on MJX's own frames", _paid(out["real"]["paid"]), "", "", "", "", ""])
    ks = ", ".join(str(k) for k in decisions)
    return _table(["setting", "real success of the imagined actions (95% interval)", "the detector said",
                   "real failures it called successes", f"frame error, decisions {ks}",
                   f"greedy action gap, decisions {ks}", "paid against the first, points (paired 95%)"], rows)


CLOSED_LOOP_WORLD_MODELS = ("policy", "closed_loop_world_models_small_h200")
# its launch.sh's four world models, one folder each, trained on the same data, VAE and latents
# run -> (its row's words, its column's words)
CLOSED_LOOP_WORLD_MODEL_RUNS = {
    "a": ("DLB as configured (the cache written with the one-step estimate)", "DLB (one-step writes)"),
    "b": ("DLB, the cache written with the flow sampler's own samples (5 Euler steps, as inference)",
          "DLB (sampler writes)"),
    "c": ("teacher forcing (DLB off)", "teacher forcing"),
    "d": ("DLB as configured, with WoVR's context noise (std 0.1)", "DLB + context noise"),
}


def _world_model_figures(record: tuple[str, ...], last_steps: int = 500) -> dict:
    """A world-model run's training loss (mean over its last ``last_steps`` logged steps) and its last evaluation's
    one-call sample error (5 Euler steps, real context) on fixed held-out expert and policy segments."""
    rows, measured = _world_model_metrics(record, ("world_model_metrics.jsonl",))
    end = max(r["step"] for r in rows)
    losses = [r["loss"] for r in rows if "loss" in r and r["step"] > end - last_steps]
    evaluated = measured[max(measured)]
    return dict(steps=end, loss=sum(losses) / len(losses), expert=evaluated["eval_heldout_sample_error_5"],
                policy=evaluated["eval_policy_sample_error_5"])


def closed_loop_world_models(record: tuple[str, ...] = CLOSED_LOOP_WORLD_MODELS,
                             decisions: tuple[int, ...] = (1, 6, 11)) -> str:
    """Four world models trained on one pipeline's latents (``CLOSED_LOOP_WORLD_MODEL_RUNS``), each measured by
    ``bench_closed_loop`` on the same starts and keys: its training loss and one-call error on real context, then in
    GRPO's closed loop the frame error and greedy action gap at ``decisions``, what reality paid the imagined actions
    and what the detector said; then the policy on MJX's own frames (run ``a``'s ``real`` row)."""
    rows, real = [], None
    for run, (what, _) in CLOSED_LOOP_WORLD_MODEL_RUNS.items():
        out = _load(*record, run, "closed_loop.json")
        real = real or out.get("real")
        v, fig = out["variants"][0], _world_model_figures((*record, run))
        by = {d["decision"]: d for d in v["decisions"]}
        false, failures = _false_successes(v)
        rows.append([what, f"{fig['loss']:.3f}", f"{fig['expert']:.4f} / {fig['policy']:.4f}",
                     " / ".join(f"{by[k]['frame_error']:.3f}" for k in decisions),
                     " / ".join(f"{by[k]['action_gap']:.3f}" for k in decisions),
                     _paid(v["paid"]), f"{v['detector']['rate']:.3f}", f"{false / failures:.3f}"])
    rows.append(["the policy on MJX's own frames", "", "", "", "", _paid(real["paid"]), "", ""])
    ks = ", ".join(str(k) for k in decisions)
    return _table(["world model's training (5,000 steps)", "loss, last 500 steps",
                   "one-call sample error on real context: held-out expert / policy segments",
                   f"closed loop: frame error, decisions {ks}", f"greedy action gap, decisions {ks}",
                   "real success of the imagined actions (95% interval)", "the detector said",
                   "real failures it called successes"], rows)


def closed_loop_world_models_decisions(record: tuple[str, ...] = CLOSED_LOOP_WORLD_MODELS) -> str:
    """Per decision the closed loop's frame error in each of ``CLOSED_LOOP_WORLD_MODEL_RUNS``' world models (the same
    starts, actions chosen on each one's own frames), with the real motion and the VAE's floor (run ``a``'s)."""
    runs = {run: {d["decision"]: d for d in _load(*record, run, "closed_loop.json")["variants"][0]["decisions"]}
            for run in CLOSED_LOOP_WORLD_MODEL_RUNS}
    first = runs["a"]
    rows = [[str(k), *(f"{runs[run][k]['frame_error']:.3f}" for run in runs), f"{first[k]['motion']:.3f}",
             f"{first[k]['frame_error_vae']:.3f}"] for k in sorted(first)]
    return _table(["decision", *(f"frame error: {CLOSED_LOOP_WORLD_MODEL_RUNS[run][1]}" for run in runs),
                   "real motion over the decision",
                   "the VAE alone"], rows)


# each VAE's run: its row's words -> the record's path
START_LATENTS = {"small, 8x VAE (600 steps; one H200)": ("policy", "closed_loop_starts_small_h200", "start_latents.json"),
                 "tiny (2,000 steps; 2-core CPU)": ("policy", "start_latents_tiny_cpu", "start_latents.json")}


def start_latents(records: dict[str, tuple[str, ...]] = START_LATENTS) -> str:
    """``bench_start_latents`` on each VAE of ``records``: per keyframe, how far each way of encoding GRPO's start
    context is from the whole episode's latent there (relative error, median and largest over the episodes)."""
    rows = [[vae, f"{r['frame']} (latent {r['latent']})", str(r["episodes"]),
             *(f"{r[way]['median']:.3f} ({r[way]['max']:.3f})" for way in ("window", "still", "prefix"))]
            for vae, record in records.items() for r in _load(*record)["rows"]]
    return _table(["VAE", "keyframe: frame", "episodes", "window (the default): median (largest)",
                   "the keyframe held still", "from the first frame (start_encoding=prefix)"], rows)


CLOSED_LOOP_STARTS = ("policy", "closed_loop_starts_small_h200")
# its launch.sh's closed-loop runs: folder -> (world model's training steps, {variant: its row's words})
CLOSED_LOOP_STARTS_RUNS = {
    "loop_5k": ("5,000", {"w": "window starts (the default)", "p": "prefix starts"}),
    "loop_10k": ("10,000", {"p": "prefix starts"}),
    "loop_10k_sampler": ("10,000", {"s10": "prefix starts, 10 Euler steps a chunk (5 configured)",
                                    "n0": "prefix starts, noise scale 0 (one deterministic sample)"}),
}


def closed_loop_starts(record: tuple[str, ...] = CLOSED_LOOP_STARTS, decisions: tuple[int, ...] = (1, 6, 11)) -> str:
    """GRPO's closed loop through one pipeline's world models (``CLOSED_LOOP_STARTS_RUNS``) from the same keyframes and
    keys: per setting its start context's error, at ``decisions`` the frame error, the greedy action gap, where the
    state probe puts the arm against the real frame and how often it reads the gripper alike, then what reality paid
    the imagined actions, what the detector said and the real failures it called successes; then the policy on MJX's
    own frames, and the floors (the VAE's frame error and the probe's held-out error on real frames)."""
    rows, real, vae = [], None, None
    for folder, (steps, names) in CLOSED_LOOP_STARTS_RUNS.items():
        out = _load(*record, folder, "closed_loop.json")
        real = real or out.get("real")
        for v in out["variants"]:
            by = {d["decision"]: d for d in v["decisions"]}
            vae = vae or by
            false, failures = _false_successes(v)
            cell = lambda key, form: " / ".join(form.format(by[k][key]) for k in decisions)  # noqa: E731
            rows.append([steps, names[v["name"]], f"{v['start_context_error']:.3f}", cell("frame_error", "{:.3f}"),
                         cell("action_gap", "{:.3f}"), cell("ee_cm", "{:.1f}"), cell("gripper_agree", "{:.2f}"),
                         _paid(v["paid"]), f"{v['detector']['rate']:.3f}", f"{false / failures:.3f}"])
    probe = _load(*record, "stages", "probe.json")["results"]
    rows.append(["", "floors: the VAE's round trip of the real frames; the probe on held-out real frames", "",
                 " / ".join(f"{vae[k]['frame_error_vae']:.3f}" for k in decisions), "",
                 f"{probe['holdout_ee_cm']:.1f}", f"{probe['holdout_gripper_acc']:.2f}", "", "", ""])
    rows.append(["", "the policy on MJX's own frames", "", "", "", "", "", _paid(real["paid"]), "", ""])
    ks = ", ".join(str(k) for k in decisions)
    return _table(["world model's training steps", "setting", "start context against training's (relative)",
                   f"frame error, decisions {ks}", f"greedy action gap, decisions {ks}",
                   f"arm: probe's reading apart, cm, decisions {ks}", f"gripper read alike, decisions {ks}",
                   "real success of the imagined actions (95% interval)", "the detector said",
                   "real failures it called successes"], rows)


ACTION_CONDITIONING = ("policy", "action_conditioning_small_h200")
# its launch.sh's world models (each 5,000 steps on the same latents) and closed-loop runs:
# folder -> (world model's words, its metrics folder, {variant: its row's words})
ACTION_CONDITIONING_RUNS = {
    "loop_base": ("DLB (the pipeline's)", "wm", {"p": "prefix starts"}),
    "loop_nodlb": ("no DLB cache", "wm_nodlb", {"p": "prefix starts"}),
    "loop_ad": ("DLB, action dropout 0.1", "wm_ad", {"g1": "prefix starts, no guidance",
                                                      "g2": "prefix starts, action guidance 2",
                                                      "g3": "prefix starts, action guidance 3"}),
}


def _last_eval(record: tuple[str, ...], folder: str) -> dict:
    """The last held-out evaluation a world model's trainer logged (its ``world_model_metrics.jsonl``)."""
    with open(os.path.join(RESULTS_DIR, *record, folder, "world_model_metrics.jsonl")) as f:
        rows = [json.loads(line) for line in f if line.strip()]
    return [r for r in rows if "eval_heldout_sample_error_5" in r][-1]


def action_conditioning(record: tuple[str, ...] = ACTION_CONDITIONING, decisions: tuple[int, ...] = (1, 6, 11)
                        ) -> str:
    """World models of one pipeline's latents under three training rules (``ACTION_CONDITIONING_RUNS``): the one-call
    sample error on held-out expert / policy segments at 5 Euler steps and the same call under other segments'
    actions (the ratio: how much the actions decide the prediction), then GRPO's closed loop from the same starts and
    keys: at ``decisions`` the frame error, greedy action gap, arm apart and gripper read alike (the state probe),
    what reality paid the imagined actions, what the detector said and the real failures it called successes; then
    the floors (the VAE's round trip read by the probe) and the policy on MJX's own frames."""
    rows, real, floor = [], None, None
    for folder, (model, metrics, names) in ACTION_CONDITIONING_RUNS.items():
        out = _load(*record, folder, "closed_loop.json")
        real = real or out.get("real")
        ev = _last_eval(record, metrics)
        one_call = " / ".join(f"{ev[f'eval_{split}_sample_error_5']:.4f}" for split in ("heldout", "policy"))
        ratio = " / ".join(f"{ev[f'eval_{split}_other_actions_error_5'] / ev[f'eval_{split}_sample_error_5']:.2f}"
                           for split in ("heldout", "policy"))
        for v in out["variants"]:
            by = {d["decision"]: d for d in v["decisions"]}
            floor = floor or by
            false, failures = _false_successes(v)
            cell = lambda key, form: " / ".join(form.format(by[k][key]) for k in decisions)  # noqa: E731
            rows.append([model, names[v["name"]], one_call, ratio, cell("frame_error", "{:.3f}"),
                         cell("action_gap", "{:.3f}"), cell("ee_cm", "{:.1f}"), cell("gripper_agree", "{:.2f}"),
                         _paid(v["paid"]), f"{v['detector']['rate']:.3f}", f"{false / failures:.3f}"])
    rows.append(["floors", "the real frames through the VAE, read by the same policy and probe", "", "",
                 " / ".join(f"{floor[k]['frame_error_vae']:.3f}" for k in decisions),
                 " / ".join(f"{floor[k]['action_gap_vae']:.3f}" for k in decisions),
                 " / ".join(f"{floor[k]['ee_cm_vae']:.1f}" for k in decisions),
                 " / ".join(f"{floor[k]['gripper_agree_vae']:.2f}" for k in decisions), "", "", ""])
    rows.append(["", "the policy on MJX's own frames", "", "", "", "", "", "", _paid(real["paid"]), "", ""])
    ks = ", ".join(str(k) for k in decisions)
    return _table(["world model (5,000 steps)", "setting", "one-call error, held-out expert / policy",
                   "other segments' actions: error ratio, expert / policy", f"frame error, decisions {ks}",
                   f"greedy action gap, decisions {ks}", f"arm: probe's reading apart, cm, decisions {ks}",
                   f"gripper read alike, decisions {ks}", "real success of the imagined actions (95% interval)",
                   "the detector said", "real failures it called successes"], rows)


HORIZON_SIGNAL = ("policy", "grpo_horizon_signal_small_cpu")
HORIZON_SIGNAL_GROUPS = 32  # its run.sh's --rl.grpo.rollout_batch: start states (groups of 8) a step
HORIZON_SIGNAL_STARTS = {2: "every phase", 4: "every phase", 12: "the first half (the learned simulator's setting)"}


def grpo_horizon_signal() -> str:
    """Ground-truth GRPO's first steps at each rollout horizon (``train_history.jsonl`` of ``h<decisions>``): what
    its rollouts succeeded and how many of its groups had mixed outcomes, the only ones with a learning signal."""
    rows = []
    for horizon, starts in HORIZON_SIGNAL_STARTS.items():
        with open(os.path.join(RESULTS_DIR, *HORIZON_SIGNAL, f"h{horizon}", "train_history.jsonl")) as f:
            history = [json.loads(line) for line in f if line.strip()]
        rows.append([f"{horizon} ({4 * horizon} actions)", starts,
                     ", ".join(f"{h['rollout_success']:.3f}" for h in history),
                     ", ".join(f"{int(h['mixed_groups'])} of {HORIZON_SIGNAL_GROUPS}" for h in history)])
    return _table(["horizon, decisions", "keyframes from", "rollout success, steps 1 and 2",
                   "groups with mixed outcomes"], rows)


# the reward-source experiment's gt and exec arms at several horizons of 8 actions a decision from keyframes of every
# phase, 64 starts x 8, 4 steps, seed 0 (bench_grpo_reward_source horizons over its work dirs)
HORIZON_HONESTY = ("policy", "grpo_horizon_honesty_small_2xh200", "horizons.json")


def _detector_cell(detector: dict | None) -> str:
    """The detector's ``success / agreement / precision`` on rollouts that reality paid (precision ``n/a`` where it
    said no success), and the AUC of its scores against the real outcomes where the steps recorded it; empty
    without it."""
    if not detector:
        return ""
    precision = "n/a" if detector["precision"] is None else f"{detector['precision']:.2f}"
    auc = detector.get("auc")  # recorded by executed steps since the detector's separation was measured
    return (f"{detector['success']:.2f} / {detector['agreement']:.2f} / {precision}"
            + (f"; AUC {auc:.2f}" if auc is not None else ""))


def grpo_horizon_honesty(record: tuple[str, ...] = HORIZON_HONESTY) -> str:
    """Per horizon of a ``bench_grpo_reward_source horizons`` record (``record``: its ``horizons.json``), by the
    actions a rollout executes: what reality paid the training rollouts on real frames and on the world model's
    (pooled over every step, 95% Wilson interval), the share of the first the world model's frames kept, the groups
    with mixed outcomes per step (median) on each, and the detector on the world model's rollouts."""
    rows = []
    for r in _load(*record)["rows"]:
        gt, ex = (r["arms"].get(arm) for arm in ("gt", "exec"))
        kept = r["exec_over_gt"]
        rows.append([f"{r['decisions']} x {r['actions_per_decision']} = {r['actions']}",
                     *(_paid(a["paid_success"]) if a else "not run" for a in (gt, ex)),
                     "" if kept is None else f"{kept:.2f}",
                     *(f"{a['mixed_groups_median']:g} of {r['groups_per_step']}" if a else "" for a in (gt, ex)),
                     _detector_cell(ex.get("detector") if ex else None)])
    return _table(["decisions x actions = actions a rollout executes",
                   "real success paid on real frames, all steps (95% interval)",
                   "on the world model's frames, its actions executed", "share kept (world model / real)",
                   "groups mixed a step (median), real frames", "world model's frames",
                   "the detector on the world model's rollouts: success / agreement / precision"], rows)


def _branched_rows(entry: dict, arms: Sequence[str], cells: Callable[[dict], list[str]]) -> list[list[str]]:
    """Rows of a ``bench_grpo_value`` entry, arm by arm and seed by seed: label, seed, steps, then ``cells(run)``."""
    return [[entry["arms"][arm]["label"], f"s{run['seed']}", str(run["steps"]), *cells(run)]
            for arm in arms for _, run in sorted(entry["runs"].items()) if run["arm"] == arm]


def _gain_cell(point: dict) -> str:
    return f"{_pct(point['gain'])} {_interval(point['ci95'])}"


def _masked_cell(run: dict) -> str:
    masked = run["sampled_proprio_masked"]
    return f"{masked['start']:.3f} -> {masked['end']:.3f}, {_gain_cell(masked)}"


def _paid_cell(run: dict) -> str:
    paid, value_paid = run["paid_success"], run.get("terminal_value")
    return (f"{paid['first']:.3f} -> {paid['last']:.3f}"
            + (f" (value {value_paid['first']:.3f} -> {value_paid['last']:.3f})" if value_paid else ""))


def grpo_branched_value() -> str:
    """Branched short ground-truth GRPO closed by the fitted value against paid by success alone
    (``policy_grpo_branched_value_small``): per run the gains of the sampled policy with proprio masked (the mode
    its rollouts train) and with true proprio, what its rollouts were paid, its groups with mixed outcomes, and the
    value's held-out calibration."""
    def cells(run):
        v = run["value"]
        return [_masked_cell(run), _gain_cell(run["sampled"]), _paid_cell(run), f"{run['mixed_median']:.2f}",
                f"{v['held_out_brier']:.3f} / {v['held_out_brier_constant']:.3f} / {v['held_out_auc']:.2f}"]

    rows = _branched_rows(_load("latest.json")["policy_grpo_branched_value_small"], ("value", "success"), cells)
    return _table(["rollouts (4 decisions, branched from the policy's real states)", "seed", "steps",
                   "sampled success, proprio masked: start -> end, gain (points)", "sampled, true proprio: gain",
                   "paid success, steps 1-5 -> last 5", "groups mixed (median)",
                   "value held out: Brier / constant's / AUC"], rows)


# the open-starts entries and how their runs differ: starts a step (bench_grpo_value --rollout-batch), KL anchor
BRANCHED_OPEN = {"policy_grpo_branched_open_small": "64 starts x 8, 4 decisions",
                 "policy_grpo_branched_open_b256_small": "256 starts x 8, 4 decisions",
                 "policy_grpo_branched_open_b1024_small": "1,024 starts x 8, 4 decisions",
                 "policy_grpo_branched_open_h12_small": "256 starts x 8, 12 decisions",
                 "policy_grpo_rest_h12_small": "256 starts x 8, 12 decisions",
                 "policy_grpo_rest_whole_small": "64 starts x 8, to the episode limit",
                 "policy_grpo_branched_open_kl_small": "64 starts x 8, 4 decisions, KL 0.04 to the start"}


def grpo_branched_open() -> str:
    """The same comparison with starts where the value says the outcome is open and centred advantages
    (``policy_grpo_branched_open_small``, ``..._open_b256_small`` at 256 starts a step, ``..._open_b1024_small`` at
    1,024, ``..._open_h12_small`` at 256 with 12-decision rollouts and ``..._open_kl_small`` anchored by a KL term;
    ``policy_grpo_rest_h12_small`` and ``..._rest_whole_small``: the same setting from rest): per run the gains of the
    sampled policy with proprio masked and with true proprio and of the greedy policy, what its rollouts were paid,
    its groups with mixed outcomes and the share of the advantages' mass in groups split by real success."""
    def cells(run):
        return [_masked_cell(run), _gain_cell(run["sampled"]), _gain_cell(run["greedy"]), _paid_cell(run),
                f"{run['mixed_median']:.2f}", f"{run['success_advantage_share']:.2f}"]

    results, rows = _load("latest.json"), []
    for key, setting in BRANCHED_OPEN.items():
        if key in results:
            rows += [[f"{row[0]}, {setting}", *row[1:]]
                     for row in _branched_rows(results[key], ("success", "shuffled", "value"), cells)]
    return _table(["rollouts (centred advantages; branched: from open starts)", "seed", "steps",
                   "sampled success, proprio masked: start -> end, gain (points)", "sampled, true proprio: gain",
                   "greedy: gain", "paid success, steps 1-5 -> last 5", "groups mixed (median)",
                   "advantage mass in groups split by success"], rows)


NOISE_CONTROL_MODES = {"sampled_proprio_masked": "sampled, proprio masked", "sampled": "sampled, true proprio",
                       "greedy": "greedy"}


def grpo_noise_control() -> str:
    """Each arm of ``policy_grpo_branched_open_small`` against the noise-only control (its ``contrasts``): per
    evaluated policy the mean over seeds of the arm's real-success gain minus the control's, with a 95% interval,
    and the seeds' own differences."""
    entry = _load("latest.json")["policy_grpo_branched_open_small"]
    rows = []
    for arm, c in entry["contrasts"].items():
        for mode, label in NOISE_CONTROL_MODES.items():
            if mode in c:
                d = c[mode]
                rows.append([entry["arms"][arm]["label"], label, ", ".join(f"s{s}" for s in c["seeds"]),
                             str(c["steps"]), f"{_pct(d['mean'])} {_interval(d['ci95'])}",
                             ", ".join(_pct(d["per_seed"][str(s)]) for s in c["seeds"])])
    return _table(["arm (4 decisions from open starts, 64 x 8)", "policy evaluated", "seeds", "steps",
                   "gain minus the control's, mean (points)", "per seed"], rows)


GRADIENT_SIGNAL = ("policy", "grpo_gradient_signal_small_cpu", "gradient_signal.json")
GRADIENT_SIGNAL_LABELS = {
    "rest": "whole episodes from rest, paid success (the recipe that lifts)",
    "short": "first {h} decisions from keyframes of every phase, paid success within them (GRPO's short rollout)",
    "short_eventual": "the same decisions, paid the episode's eventual success (a perfect value)",
    "full": "every decision from those keyframes, paid the eventual success"}


def grpo_gradient_signal() -> str:
    """Per setting of ``benchmarks.bench_grpo_gradient_signal``: its groups, mixed groups, the signal fraction of one
    group's gradient, the expected cosine of two batches, the alignment of its expected gradient with the from-rest one
    and one batch's expected cosine with it (95% bootstrap intervals)."""
    with open(os.path.join(RESULTS_DIR, *GRADIENT_SIGNAL)) as f:
        probe = json.load(f)

    def value(name: str, key: str, digits: int = 3) -> str:
        v, (lo, hi) = probe["statistics"][name][key], probe["intervals"][name][key]
        ends = ", ".join("undefined" if x == float("-inf") else f"{x:.{digits}f}" for x in (lo, hi))
        return ("undefined" if v is None else f"{v:.{digits}f}") + f" [{ends}]"

    rows = []
    for name in probe["statistics"]:
        out = probe["outcomes"][name]
        rows.append([GRADIENT_SIGNAL_LABELS[name].format(h=probe["horizon_decisions"]), f"{out['paid_success']:.3f}",
                     f"{out['mixed_groups']} of {probe['statistics'][name]['groups']}",
                     value(name, "signal_fraction", 4), value(name, "cos_at_batch"),
                     "1 (the reference)" if name == "rest" else value(name, "alignment"), value(name, "useful")])
    batch = probe["batch_groups"]
    return _table(["rollouts", "paid success", "groups mixed", "one group's signal fraction",
                   f"cosine of two {batch}-group batches", "alignment with the from-rest gradient",
                   f"one {batch}-group batch's cosine with the from-rest gradient"], rows)


VALUE_SIGNAL = ("policy", "value_signal_small_cpu", "value_signal.json")


def value_signal() -> str:
    """Per fit of the value (``benchmarks.bench_value_signal``): how it ranks held-out episodes, and at the short
    rollout's horizon how it orders the trajectories of one group by their later outcome against every pair."""
    with open(os.path.join(RESULTS_DIR, *VALUE_SIGNAL)) as f:
        probe = json.load(f)
    rows = []
    for name, fit in probe["fits"].items():
        steps, seed = re.fullmatch(r"steps(\d+)_seed(\d+)", name).groups()
        held, within, across = fit["held_out"], fit["within_group_auc"], fit["across_all_auc"]
        rows.append([f"{int(steps):,}", seed, f"{held['auc']:.3f}", f"{held['brier']:.3f} / {held['brier_constant']:.3f}",
                     f"{within['auc']:.3f} ({within['pairs']} pairs)", f"{across['auc']:.3f} ({across['pairs']:,} pairs)",
                     f"{fit['within_group_variance_share']:.2f}"])
    return _table(["fit steps", "fit seed", "held-out episodes: AUC", "Brier / constant's",
                   "at the horizon: within-group AUC", "across all pairs", "share of the value's variance within groups"],
                  rows)


def sim_fidelity_decisions(run: tuple[str, ...] = (*SIM_FIDELITY, "exec_vae8x")) -> str:
    """Per decision of a closed loop paid by execution (``run``: its work dir under the results; by default the 8x
    VAE's ``exec_vae8x``), the mean over its steps: the frame the policy read and its greedy actions on it against
    the real frame, the VAE alone's share, and the real motion."""
    history = _history_rows(os.path.join(RESULTS_DIR, *run, "rl", "grpo", "train_history.jsonl"))
    decisions = _closed_loop_decisions(history)

    def mean(what: str, k: int) -> str:
        return f"{statistics.mean(h[f'closed_loop_{what}_{k}'] for h in history):.3f}"

    rows = [[str(k), mean("frame_error", k), mean("frame_error_vae", k), mean("motion", k), mean("action_gap", k),
             mean("action_gap_vae", k), mean("action_gap_prev", k)] for k in decisions]
    return _table(["decision", "frame error to the real frame", "the VAE alone", "real motion over the decision",
                   "greedy action gap to the real frame", "the VAE alone", "to the real frame a decision earlier"], rows)


# the reward-source experiment from the demonstrations' first keyframe, 12 decisions, one seed (one H200)
REWARD_SOURCE_REST = ("policy", "grpo_reward_source_rest_small_h200")


def _history_rows(history_path: str, upto: int = 0) -> list[dict]:
    """The rows of a GRPO run's ``train_history.jsonl`` (with ``upto``, those to that step)."""
    with open(history_path) as f:
        return [h for h in (json.loads(line) for line in f if line.strip()) if not upto or h["step"] <= upto]


def _paid_over_steps(history: list[dict]) -> dict:
    """What reality paid every training rollout of a ground-truth GRPO run (``rollout_success`` of each step of its
    history, times ``trajectories_sampled``): ``{"rate", "ci95", "of"}`` with a Wilson interval."""
    from sword_jax.rl.env_rollout import wilson_interval

    of = sum(int(h["trajectories_sampled"]) for h in history)
    hits = round(sum(h["rollout_success"] * h["trajectories_sampled"] for h in history))
    return {"rate": hits / of, "ci95": list(wilson_interval(hits, of)), "of": of}


def grpo_reward_source_rest() -> str:
    """The reward-source experiment from the first keyframe at 12 decisions (``REWARD_SOURCE_REST``): what reality
    paid every rollout on real frames and on the world model's, the groups left mixed, the gains at step 20 and the
    detector on the world model's rollouts."""
    summary = _load(*REWARD_SOURCE_REST, "grpo_reward_source.json")
    loop = next(iter(_load(*REWARD_SOURCE_REST, "closed_loop.json")["runs"].values()))
    labels = {"gt": "real frames, real reward (ground-truth GRPO on MJX)",
              "exec": "the world model's frames, the real outcome of their actions"}
    rows = []
    for name, run in sorted(summary["runs"].items(), key=lambda kv: list(labels).index(kv[1]["arm"])):
        if run["arm"] == "gt":
            gt = _run_dir(*REWARD_SOURCE_REST, "gt", f"s{run['seed']}")
            paid = _paid_over_steps(_history_rows(os.path.join(gt, "train_history.jsonl")))
        else:
            paid = loop["paid_success"]
        det = run.get("detector")
        rows.append([labels[run["arm"]], f"s{run['seed']}", str(run["steps"]), _paid(paid),
                     f"{run['paid_success']['first']:.3f} -> {run['paid_success']['last']:.3f}",
                     f"{run['mixed_median']:.2f}",
                     *(f"{run[m]['start']:.2f} -> {run[m]['end']:.2f}, {_pct(run[m]['gain'])} {_interval(run[m]['ci95'])}"
                       for m in ("sampled_proprio_masked", "greedy")),
                     f"{det['success']:.2f} / {det['precision']:.2f}" if det else ""])
    return _table(["GRPO's frames and reward", "seed", "steps", "real success of the rollouts, all steps (95% interval)",
                   "steps 1-5 -> last 5", "groups mixed (median)",
                   "sampled, proprio masked: step 0 -> 20, gain (points), 100 episodes", "greedy: the same",
                   "the detector on the same rollouts: success / precision"], rows)


# the levers' run: one world model of 20,000 steps with an EMA, read by exec runs at 4 and 8 actions a decision,
# beside the 12,000-step one of REWARD_SOURCE_REST over the same first steps; per run of its closed_loop.json, in
# order, its folder (holding exec_s0/rl/grpo) and whether that folder holds the run's summary
REWARD_SOURCE_LEVERS = ("policy", "grpo_reward_source_levers_small_h200")
LEVERS_RUNS = ((REWARD_SOURCE_REST, False), (REWARD_SOURCE_LEVERS, True), ((*REWARD_SOURCE_LEVERS, "chunk"), True))
# the next world model: 30,000 steps with an EMA at 8 actions a decision, beside the levers' 20,000-step one
REWARD_SOURCE_LENGTH = ("policy", "grpo_reward_source_30k_small_h200")
LENGTH_RUNS = (((*REWARD_SOURCE_LEVERS, "chunk"), True), (REWARD_SOURCE_LENGTH, True))


def _world_model_runs(record: tuple[str, ...], runs: tuple) -> str:
    """World-model exec runs from the first real frame over the same first GRPO steps (``record``'s
    ``closed_loop.json``, its runs in the order of ``runs``: each one's folder and whether it holds the run's
    summary): per world model and actions a decision, what reality paid the imagined actions (the real frames'
    ground-truth run over the same steps first), the groups left mixed, what the detector said, the closed loop's
    first and last decisions and the sampled gain where the run was last evaluated."""
    loop = _load(*record, "closed_loop.json")
    upto = loop["first_steps"]
    gt_rows = _history_rows(os.path.join(_run_dir(*REWARD_SOURCE_REST, "gt", "s0"), "train_history.jsonl"), upto)
    rows = [["real frames (ground-truth GRPO on MJX, the 12,000-step run's arm)", "", "4 (12 decisions)",
             _paid(_paid_over_steps(gt_rows)),
             f"{statistics.median(h['mixed_groups'] for h in gt_rows):.0f} of 64", "", "", "", ""]]
    for (label, r), (folder, summarised) in zip(loop["runs"].items(), runs, strict=True):
        per, decisions = r["actions_per_decision"], r["per_decision"]["decisions"][-1] + 1  # decision 0 not recorded
        grpo = os.path.join(RESULTS_DIR, *folder, "exec_s0", "rl", "grpo")
        mixed = statistics.median(h["mixed_groups"] for h in _history_rows(os.path.join(grpo, "train_history.jsonl"), upto))
        run = summarised and _load(*folder, "grpo_reward_source.json")["runs"]["exec_s0"]
        gain = (f"step {run['steps']}: {run['sampled']['start']:.2f} -> {run['sampled']['end']:.2f}, "
                f"{_pct(run['sampled']['gain'])} {_interval(run['sampled']['ci95'])}" if run else "its own table: grpo-reward-source-rest")
        rows.append([label, f"{r['world_model_steps']:,}, loss {r['world_model_loss']:.3f}", f"{per} ({decisions} decisions)",
                     _paid(r["paid_success"]), f"{mixed:.0f} of 64", f"{r['detector_success']:.2f}",
                     f"{r['frame_error_first']:.3f} -> {r['frame_error_last']:.3f}",
                     f"{r['action_gap_first']:.3f} -> {r['action_gap_last']:.3f}", gain])
    return _table(["GRPO's frames", "world model: steps, loss (last 10 logged)", "actions a decision",
                   f"real success of the rollouts, steps 1-{upto} (95% interval)", "groups mixed (median)",
                   "the detector said", "frame error: first -> last decision", "greedy action gap: the same",
                   "sampled: step 0 -> the last evaluated, gain (points), 100 episodes"], rows)


def grpo_reward_source_levers() -> str:
    """The world model's levers (``REWARD_SOURCE_LEVERS``): the 12,000-step world model against the 20,000-step
    one with an EMA, at 4 and 8 actions a decision (:func:`_world_model_runs`)."""
    return _world_model_runs(REWARD_SOURCE_LEVERS, LEVERS_RUNS)


def grpo_reward_source_length() -> str:
    """The 30,000-step world model with an EMA at 8 actions a decision against the 20,000-step one
    (``REWARD_SOURCE_LENGTH``, :func:`_world_model_runs`)."""
    return _world_model_runs(REWARD_SOURCE_LENGTH, LENGTH_RUNS)


# the 30,000-step world model again, its trainer measuring fixed held-out and training segments every 1,000 steps
WORLD_MODEL_HELDOUT = ("policy", "world_model_heldout_30k_small_h200")
HELDOUT_STEPS = (1000, 2000, 5000, 10000, 20000, 30000)


def _world_model_metrics(record: tuple[str, ...], file: tuple[str, ...] = ("pipeline", "world_model", "metrics.jsonl")
                         ) -> tuple[list[dict], dict[int, dict]]:
    """``record``'s world-model metrics (``file`` in it, the pipeline's ``metrics.jsonl`` by default): every logged
    row, and the rows of the steps where the trainer measured its fixed segments (:mod:`sword_jax.world_model.heldout`)
    by step."""
    with open(os.path.join(RESULTS_DIR, *record, *file)) as f:
        logged = [json.loads(line) for line in f if line.strip()]
    return logged, {r["step"]: r for r in logged if "eval_heldout_loss" in r}


def world_model_heldout(record: tuple[str, ...] = WORLD_MODEL_HELDOUT, steps: tuple[int, ...] = HELDOUT_STEPS) -> str:
    """The world model measured while it trained (``record``'s ``pipeline/world_model/metrics.jsonl``,
    :mod:`sword_jax.world_model.heldout`), at ``steps``: the logged training loss (the mean of the 10 logged
    steps to there), the fixed-noise flow loss per split measured (training, held-out, held-out policy
    rollouts where there), and the sampler's error from the true context per split at each Euler step count
    measured; a last row gives each column's change from the second-last step to the last."""
    logged, measured = _world_model_metrics(record)
    counts = sorted({int(k.rsplit("_", 1)[1]) for r in measured.values() for k in r if "_sample_error_" in k})
    from sword_jax.world_model.heldout import SPLIT_LABELS as labels

    splits = [split for split in labels if f"eval_{split}_loss" in measured[steps[-1]]]
    losses = [(f"eval_{split}_loss", f"{labels[split]} segments") for split in splits]
    columns = losses + [(f"eval_{split}_sample_error_{n}", f"{labels[split]} segments, {n} Euler steps")
                        for split in (*splits[1:], splits[0]) for n in counts]

    def logged_loss(step: int) -> float:
        upto = [r["loss"] for r in logged if r["step"] <= step and "loss" in r]
        return statistics.mean(upto[-10:])

    rows = [[f"{step:,}", f"{logged_loss(step):.4f}", *(f"{measured[step][k]:.4f}" for k, _ in columns)]
            for step in steps]
    prev, last = steps[-2], steps[-1]
    change = lambda a, b: f"{100.0 * (b / a - 1.0):+.0f}%"  # noqa: E731 - relative change
    rows.append([f"{prev:,} -> {last:,}", change(logged_loss(prev), logged_loss(last)),
                 *(change(measured[prev][k], measured[last][k]) for k, _ in columns)])
    return _table(["step", "training loss (logged, last 10)",
                   *(f"fixed-noise loss: {label}" for _, label in losses),
                   *(f"sample error: {label}" for _, label in columns[len(losses):])], rows)


# the same recipe again, its trainer also measuring the supervised policy's held-out rollouts (the "policy" split)
WORLD_MODEL_POLICY_SPLIT = ("policy", "world_model_policy_split_30k_small_h200")


def world_model_policy_split() -> str:
    """:func:`world_model_heldout` of the run whose trainer also measured the ``policy`` split
    (``WORLD_MODEL_POLICY_SPLIT``)."""
    return world_model_heldout(WORLD_MODEL_POLICY_SPLIT)


# the same recipe with 100 rollouts of the supervised policy per task in the world model's data instead of 20
WORLD_MODEL_POLICY_SCALING = (WORLD_MODEL_POLICY_SPLIT, ("policy", "world_model_policy_rollouts_100_30k_small_h200"))


def world_model_policy_scaling(records: tuple[tuple[str, ...], ...] = WORLD_MODEL_POLICY_SCALING,
                               steps: tuple[int, ...] = (5000, 10000, 20000, 30000), euler: int = 5) -> str:
    """The world models of ``records`` (each ``pipeline/config.json`` and ``pipeline/world_model/metrics.jsonl``),
    trained alike but on different numbers of the supervised policy's rollouts per task: per record and step of
    ``steps``, the sampler's error (``euler`` Euler steps, true context) per split measured, and the held-out policy
    error over the held-out expert one and over the training policy one. A split a record did not measure reads
    "not measured"."""
    from sword_jax.world_model.heldout import SPLIT_LABELS as labels

    splits = ("heldout", "policy", "trainpolicy", "train")
    unmeasured = "not measured"
    ratio = lambda a, b: unmeasured if a is None or b is None else f"{a / b:.2f}"  # noqa: E731
    rows = []
    for record in records:
        per_task = _load(*record, "pipeline", "config.json")["data"]["policy_rollouts_per_task"]
        _, measured = _world_model_metrics(record)
        for step in steps:
            error = {s: measured[step].get(f"eval_{s}_sample_error_{euler}") for s in splits}
            rows.append([str(per_task), f"{step:,}",
                         *(unmeasured if error[s] is None else f"{error[s]:.4f}" for s in splits),
                         ratio(error["policy"], error["heldout"]), ratio(error["policy"], error["trainpolicy"])])
    return _table(["policy rollouts per task", "step",
                   *(f"sample error: {labels[s]} segments, {euler} Euler steps" for s in splits),
                   f"{labels['policy']} / {labels['heldout']}", f"{labels['policy']} / {labels['trainpolicy']}"], rows)


# the same recipe (20 policy rollouts per task), the world model widened and deepened, 10,000 steps, a size per GPU
WORLD_MODEL_SIZES = (WORLD_MODEL_POLICY_SPLIT, ("policy", "world_model_size_10k_small_2xh200", "mid"),
                     ("policy", "world_model_size_10k_small_2xh200", "big"),
                     # the 120 M one on 100 of the policy's rollouts per task, its segments measured alone at the end
                     ("policy", "world_model_segments_120m_100r_10k_small_h200"))


def world_model_size(records: tuple[tuple[str, ...], ...] = WORLD_MODEL_SIZES,
                     steps: tuple[int, ...] = (5000, 10000, 30000), euler: int = 5) -> str:
    """The world models of ``records``, trained alike but of different widths and depths: per record and step of
    ``steps`` it measured, its parameters (``dit_train_small_sweep``'s count for that width and depth in
    ``latest.json``), the supervised policy's rollouts per task in its data, the sampler's error (``euler`` Euler
    steps, true context) per split and the held-out policy error over the held-out expert one. A split a record did
    not measure reads "not measured"."""
    from sword_jax.world_model.heldout import SPLIT_LABELS as labels

    counted = {(r["dim"], r["layers"]): r["params"] for r in _load("latest.json")["dit_train_small_sweep"]["rows"]}
    splits = ("heldout", "policy", "trainpolicy", "train")
    rows = []
    for record in records:
        config = _load(*record, "pipeline", "config.json")
        model, per_task = config["model"], config["data"]["policy_rollouts_per_task"]
        params = counted.get((model["dim"], model["num_layers"]))
        _, measured = _world_model_metrics(record)
        for step in (s for s in steps if s in measured):
            error = {s: measured[step].get(f"eval_{s}_sample_error_{euler}") for s in splits}
            rows.append([f"{model['dim']:,} x {model['num_layers']}",
                         "not measured" if params is None else f"{params / 1e6:.1f} M", str(per_task), f"{step:,}",
                         *("not measured" if error[s] is None else f"{error[s]:.4f}" for s in splits),
                         f"{error['policy'] / error['heldout']:.2f}"])
    return _table(["world model (width x layers)", "parameters", "policy rollouts per task", "step",
                   *(f"sample error: {labels[s]} segments, {euler} Euler steps" for s in splits),
                   f"{labels['policy']} / {labels['heldout']}"], rows)


# the 120 M world model on 100 of the policy's rollouts per task: every fixed segment's error at 10,000 steps, joined
# with its episode's outcome (benchmarks.segment_errors)
WORLD_MODEL_SEGMENTS = ("policy", "world_model_segments_120m_100r_10k_small_h200")
SEGMENT_GROUPS = {"heldout": ("all", "first 48 actions", "after 48 actions"),
                  "policy": ("all", "first 48 actions", "after 48 actions", "before success", "spans success",
                             "after success", "failed episode", "failed episode, first 48 actions",
                             "failed episode, after 48 actions", "stage: before the grasp", "stage: grasped",
                             "stage: over the plate", "stage: after a release"),
                  "trainpolicy": ("all", "first 48 actions", "after 48 actions"),
                  "train": ("all", "first 48 actions", "after 48 actions")}


def world_model_segments(record: tuple[str, ...] = WORLD_MODEL_SEGMENTS, groups: dict = SEGMENT_GROUPS) -> str:
    """``record``'s ``segments.json`` (:mod:`benchmarks.segment_errors`): per split and group of ``groups`` that it
    holds, the segments, their energy-weighted sample error (the evaluation's figure over the group), median, the
    group's share of the split's figure and the arm's mean translation action over the segments' future (where the
    split's outcomes were joined)."""
    from sword_jax.world_model.heldout import SPLIT_LABELS as labels

    joined = _load(*record, "segments.json")
    rows = []
    for split, names in groups.items():
        held = joined["splits"].get(split, {}).get("groups", {})
        for name in (n for n in names if n in held):
            g = held[name]
            rows.append([labels[split], name, str(g["segments"]), f"{g['error']:.4f}", f"{g['median']:.4f}",
                         f"{g['share']:.0%}", "-" if g.get("motion") is None else f"{g['motion']:.3f}"])
    return _table(["split", "segments' future", "segments",
                   f"sample error, {joined['euler']} Euler steps (energy-weighted)", "median",
                   "share of the split's figure", "arm motion (mean absolute translation action)"], rows)


# GRPO's exec arm, seed 0, from the same keyframe starts: small's 30,000-step world model (BY_START) and the 120 M one
WORLD_MODEL_SIZE_BY_START = ((BY_START, "36.7 M, 30,000 steps"),
                             (("policy", "world_model_size_10k_small_2xh200", "mid"), "120.0 M, 10,000 steps"))


def world_model_size_by_start(records=WORLD_MODEL_SIZE_BY_START, truth: tuple[str, ...] = BY_START,
                              seed: int = 0) -> str:
    """Per bin of the start's step: ground truth's real success (``truth``'s ``gt`` run of ``seed``) and, per world
    model of ``records`` (each a record with a ``grpo_reward_source.json`` and its label), its ``exec`` run's rollouts
    of that seed paid by executing their actions, the share of ground truth's real success they kept and the
    detector's precision on them. The records' runs start from the same keyframes (the sampler's seed and step)."""
    def bins(record: tuple[str, ...], arm: str) -> list[dict]:
        runs = _load(*record, "grpo_reward_source.json")["runs"]
        found = [r for r in runs.values() if r["arm"] == arm and r["seed"] == seed and r.get("by_start")]
        return _by_start_pooled(found[0]["by_start"]) if found else []

    gt = {b["from_step"]: b for b in bins(truth, "gt")}
    rows = []
    for record, label in records:
        for e in bins(record, "exec"):
            g = gt.get(e["from_step"])
            if not e["rollouts"] or not (g and g["rollouts"]):
                continue
            paid_e, paid_g = e["real"] / e["rollouts"], g["real"] / g["rollouts"]
            rows.append([_bin_span(e), label, f"{g['rollouts']:,}", f"{paid_g:.3f}", f"{e['rollouts']:,}",
                         f"{paid_e:.3f}", f"{100 * paid_e / paid_g:.0f}%",
                         f"{e['said_real'] / e['said']:.2f}" if e["said"] else ""])
    rows.sort(key=lambda r: int(r[0].rstrip("+").split("-")[0]))  # stable: the records' order kept
    return _table(["start's step in its demonstration (actions)", "world model", "ground truth: rollouts",
                   "ground truth: real success", "world model, paid by execution: rollouts", "its real success",
                   "kept (world model over ground truth)", "the detector's precision"], rows)


OUTCOME_DETERMINACY = ("policy", "outcome_determinacy_small_cpu")


def outcome_determinacy(record: tuple[str, ...] = OUTCOME_DETERMINACY) -> str:
    """``bench_outcome_determinacy``'s record (``outcome_determinacy.json``): per group of starts (stage, then bin
    of the start's step in its episode, then all), its starts and reference success, and per perturbation the share
    of perturbed replays whose outcome flipped, with the share of the reference successes' replays still succeeding
    (kept) and of the reference failures' succeeding (false). A group with no start is left out."""
    d = _load(*record, "outcome_determinacy.json")
    keys = list(d["groups"]["all"]["flipped"])
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    rows = []
    for name, g in d["groups"].items():
        if not g["starts"]:
            continue
        rows.append([name, str(g["starts"]), f"{g['reference_success']:.3f}",
                     *(f"{fmt(g['flipped'][k])} ({fmt(g['kept'][k])} / {fmt(g['false_success'][k])})"
                       if g["measured_starts"][k] else "not moved" for k in keys)])
    return _table(["starts", "count", "reference success (the recorded actions from the recorded state)",
                   *(f"{k}: flipped (kept / false)" for k in keys)], rows)


# bench_failure_phases' records: the 4-decision rollouts (recorded to latest.json) and, from the same branch points,
# 8- and 12-decision ones
FAILURE_STAGE_RUNS = ("failure_phases_small_cpu", "failure_phases_h8_small_cpu", "failure_phases_h12_small_cpu")


def _failure_runs(names) -> dict[str, dict]:
    """``bench_failure_phases``' ``policy/<name>/failure_phases.json`` of those of ``names`` that are there, in order."""
    return {name: _load("policy", name, "failure_phases.json") for name in names
            if os.path.exists(os.path.join(RESULTS_DIR, "policy", name, "failure_phases.json"))}


def failure_stages() -> str:
    """Where the policy fails from rest and where short rollouts have mixed outcomes (``bench_failure_phases``'
    ``policy/<run>/failure_phases.json`` for each of :data:`FAILURE_STAGE_RUNS` there): per stage, its share of the
    failures from rest; per branch point's stage, the starts and, per rollout length, their groups with mixed
    outcomes and their paid success. Runs whose episodes or starts differ from the first's are left out."""
    runs = list(_failure_runs(FAILURE_STAGE_RUNS).values())
    d = runs[0]
    same = [r for r in runs if r["episode_stages"] == d["episode_stages"]
            and all(r["starts"][k]["starts"] == v["starts"] for k, v in d["starts"].items())]
    failed = d["episodes"] - d["episode_stages"]["success"]
    rows = [[name, f"{d['episode_stages'][name]} ({d['failure_shares'][name]:.2f} of {failed})"]
            for name in list(d["failure_shares"])]
    rows.append(["success", f"{d['episode_stages']['success']} of {d['episodes']} ({d['success']:.3f})"])
    header = [f"branch point's stage (groups of {d['group_size']})", "starts"]
    for r in same:
        header += [f"mixed groups, {r['horizon_decisions']} decisions", f"paid success, {r['horizon_decisions']}"]
    starts = [[name, str(v["starts"])] for name, v in d["starts"].items()]
    for row, name in zip(starts, d["starts"]):
        for r in same:
            v = r["starts"][name]
            row += [str(v["mixed_groups"]), "" if v["paid_success"] is None else f"{v['paid_success']:.3f}"]
    total = ["all", str(sum(v["starts"] for v in d["starts"].values()))]
    for r in same:
        total += [str(r["mixed_groups"]), ""]
    return (_table(["episodes from rest, furthest stage", "episodes"], rows) + "\n\n"
            + _table(header, starts + [total]))


# the per-task runs of bench_failure_phases (12 decisions, the same 300 episodes) and where their rollouts branched
FAILURE_TASK_RUNS = (("failure_phases_h12_small_cpu", "from running decisions"),
                     ("failure_phases_h12_rest_small_cpu", "from rest"))
TASK_NAMES = ("between the plate and the ramekin", "next to the ramekin", "table centre", "on the cookie box",
              "in the top drawer", "on the ramekin", "next to the cookie box", "on the stove", "next to the plate",
              "on the wooden cabinet")  # sim.tasks.LANGUAGE, shortened


def _task_label(task: str) -> str:
    """A task id (as the JSON keys it) with its short name."""
    return f"{task}: {TASK_NAMES[int(task)]}" if int(task) < len(TASK_NAMES) else task


# per-task gains of GRPO runs on MJX: (column, run folder under policy/, the runs' seed folders, evaluated policy,
# step or None for each run's last point)
PER_TASK_RUNS = (
    ("12 decisions, step 15: proprio masked", "grpo_branched_open_h12_seeds_small_h200", "success/s{}",
     "sampled_proprio_masked", 15),
    ("greedy", "grpo_branched_open_h12_seeds_small_h200", "success/s{}", "greedy", 15),
    ("4 decisions, 1,024 starts, last step: proprio masked", "grpo_branched_open_b1024_seeds_small_h200", "success/s{}",
     "sampled_proprio_masked", None),
    ("whole episodes, step 10: sampled (true proprio)", "grpo_mjx_seeds_small_4xh100", "s{}", "sampled", 10))
# the same from rest, one policy_d50 for both: cut at 12 decisions beside whole episodes, at step 10 and the last step
REST_PER_TASK_RUNS = (
    ("12 decisions, step 10: proprio masked", "grpo_rest_h12_seeds_small_2xh200", "success/s{}",
     "sampled_proprio_masked", 10),
    ("whole episodes, step 10: proprio masked", "grpo_rest_whole_seeds_small_2xh200", "success/s{}",
     "sampled_proprio_masked", 10),
    ("12 decisions, step 10: greedy", "grpo_rest_h12_seeds_small_2xh200", "success/s{}", "greedy", 10),
    ("whole episodes, step 10: greedy", "grpo_rest_whole_seeds_small_2xh200", "success/s{}", "greedy", 10),
    ("12 decisions, last step: proprio masked", "grpo_rest_h12_seeds_small_2xh200", "success/s{}",
     "sampled_proprio_masked", None))


def _run_dir(*parts: str) -> str:
    """The folder of the GRPO run under ``<results>/<parts>``: the one holding a ``success_curve.json``."""
    run = os.path.join(RESULTS_DIR, *parts)
    name = next(d for d in sorted(os.listdir(run)) if os.path.exists(os.path.join(run, d, "success_curve.json")))
    return os.path.join(run, name)


def _curve_points(folder: str, seed_dir: str) -> list[dict]:
    """The evaluation points of the GRPO run under ``policy/<folder>/<seed_dir>`` (its ``success_curve.json``)."""
    with open(os.path.join(_run_dir("policy", folder, seed_dir), "success_curve.json")) as f:
        return json.load(f)["points"]


# two recipes from one policy, seeds and evaluation episodes (deterministic ops): (label, folder), the other's
# label and folder, and the step both reached
CUT_VS_WHOLE = (("12 decisions", "grpo_rest_h12_seeds_small_2xh200"),
                ("whole episodes", "grpo_rest_whole_seeds_small_2xh200"), 10)


def grpo_rest_cut_vs_whole(pair=CUT_VS_WHOLE, seeds: Sequence[int] = (0, 1, 2)) -> str:
    """The first recipe's real success minus the second's at the same step, per evaluated policy and seed, paired
    episode by episode (the same 500 episodes; both runs' step-0 outcomes must be identical, else the table
    refuses), and the mean over the seeds with a 95% interval (normal approximation from the seeds' intervals)."""
    from sword_jax.rl.env_rollout import mean_interval, paired_difference_interval, point_outcomes

    (label_a, folder_a), (label_b, folder_b), step = pair
    rows = []
    for mode, name in NOISE_CONTROL_MODES.items():
        diffs, intervals, cells = [], [], []
        for seed in seeds:
            ends = []
            for folder in (folder_a, folder_b):
                points = _curve_points(folder, f"success/s{seed}")
                ends.append((point_outcomes(_mode_point(points[0], mode)),
                             point_outcomes(_mode_point(next(p for p in points if p["step"] == step), mode))))
            (start_a, a), (start_b, b) = ends
            if any(o is None for run in ends for o in run):
                raise ValueError(f"grpo_rest_cut_vs_whole: seed {seed}'s evaluations ({mode}) kept no per-episode "
                                 "outcomes; the runs cannot be paired")
            if start_a.shape != start_b.shape or not (start_a == start_b).all():
                raise ValueError(f"grpo_rest_cut_vs_whole: seed {seed}'s step-0 outcomes ({mode}) differ between "
                                 f"{folder_a} and {folder_b}; the runs are not paired")
            low, high = paired_difference_interval(b, a)
            diff = float(a.mean() - b.mean())
            diffs.append(diff)
            intervals.append((low, high))
            cells.append(f"{a.mean():.3f} / {b.mean():.3f}, {_pct(diff)} {_interval([low, high])}")
        mean, ci95 = mean_interval(diffs, intervals)
        rows.append([name, *cells, f"{_pct(mean)} {_interval(ci95)}"])
    return _table(["policy evaluated", *(f"s{s}: {label_a} / {label_b} at step {step}, difference (points)"
                                         for s in seeds), "mean difference over the seeds"], rows)


def _mode_point(point: dict, mode: str) -> dict:
    """An evaluation point's figures for one evaluated policy: the point itself for ``greedy``, else its ``mode``
    entry (``sampled``, ``sampled_proprio_masked``)."""
    return point if mode == "greedy" else point[mode]


def _task_success(point: dict, mode: str) -> dict[str, float]:
    return _mode_point(point, mode)["per_task"]


def grpo_per_task(runs=PER_TASK_RUNS) -> str:
    """Per task, each of ``runs``' (:data:`PER_TASK_RUNS`) gains (points, seeds 0, 1 and 2) from its own step 0 to
    the step, for the policy it names, read from the runs' ``success_curve.json``; the first run's step-0 success
    (seed 0: its first column's policy / greedy) beside them."""
    columns, start = [], None
    for label, folder, seed_dir, mode, step in runs:
        gains = []
        for seed in range(3):
            points = _curve_points(folder, seed_dir.format(seed))
            end = points[-1] if step is None else next(p for p in points if p["step"] == step)
            first, last = _task_success(points[0], mode), _task_success(end, mode)
            gains.append({t: last[t] - first[t] for t in first})
            if start is None:
                start = (_task_success(points[0], mode), points[0]["per_task"])
        columns.append((label, gains))
    rows = []
    for task in sorted(start[0], key=int):
        rows.append([_task_label(task), f"{start[0][task]:.2f} / {start[1][task]:.2f}",
                     *(", ".join(f"{100 * g[task]:+.0f}" for g in gains) for _, gains in columns)])
    return _table(["task (the black bowl ...)", "start (seed 0): sampled, proprio masked / greedy",
                   *(label for label, _ in columns)], rows)


# bench_failure_phases' runs branched from rest (--branch-from rest) at several horizons, the same 300 episodes
FAILURE_REST_RUNS = ("failure_phases_h8_rest_small_cpu", "failure_phases_h12_rest_small_cpu",
                     "failure_phases_h16_rest_small_cpu")


def _rest_rollout_cells(r: dict) -> tuple[str, str, str]:
    """A ``bench_failure_phases`` run's rollouts: their horizon in decisions and actions, the groups with mixed
    outcomes over every start, and per task the mixed groups over its starts."""
    starts, tasks = sum(v["starts"] for v in r["starts"].values()), r["per_task"]
    return (f"{r['horizon_decisions']} ({r['horizon_decisions'] * r['actions_per_decision']} actions)",
            f"{r['mixed_groups']} of {starts} ({r['mixed_groups'] / starts:.2f})",
            ", ".join(f"{tasks[t]['mixed_groups']}/{tasks[t]['starts']}" for t in sorted(tasks, key=int)))


def failure_rest_horizons() -> str:
    """Per horizon of :data:`FAILURE_REST_RUNS` (those there): the groups started at rest, those with mixed outcomes,
    their paid success and the mixed groups per task."""
    rows = []
    for r in _failure_runs(FAILURE_REST_RUNS).values():
        paid = r["starts"]["before the grasp"]["paid_success"]
        horizon, mixed, per_task = _rest_rollout_cells(r)
        rows.append([horizon, mixed, "" if paid is None else f"{paid:.3f}", per_task])
    return _table(["decisions from rest", "groups with mixed outcomes", "paid success",
                   "mixed groups / starts, tasks 0-9"], rows)


# the same episodes' start states from rest, 48-action rollouts, at 4 actions a decision (the recipe's) and at a
# whole chunk of 8
FAILURE_REST_CHUNK_RUNS = ("failure_phases_h12_rest_small_cpu", "failure_phases_h6x8_rest_small_cpu")


def failure_rest_chunk() -> str:
    """Per number of actions a decision (:data:`FAILURE_REST_CHUNK_RUNS`): the episodes from rest (success with a
    Wilson interval, where the failures stopped, decisions to a success) and the rollouts from their first states
    cut at 48 actions (groups with mixed outcomes, paid success, mixed groups per task)."""
    from sword_jax.rl.env_rollout import wilson_interval

    rows = []
    for r in _failure_runs(FAILURE_REST_CHUNK_RUNS).values():
        k, stages, episodes = r["actions_per_decision"], r["episode_stages"], r["episodes"]
        low, high = wilson_interval(stages["success"], episodes)
        horizon, mixed, per_task = _rest_rollout_cells(r)
        rows.append([str(k), f"{r['success']:.3f} [{low:.3f}, {high:.3f}] of {episodes}",
                     " / ".join(str(stages[s]) for s in ("never grasped", "grasped, never over the plate",
                                                        "over the plate, not placed")),
                     ", ".join(f"{q * k:g}" for q in r["decisions_to_success"]), horizon, mixed,
                     f"{r['starts']['before the grasp']['paid_success']:.3f}", per_task])
    return _table(["actions a decision", "episodes from rest: success (95% interval)",
                   "failures: never grasped / carry failed / not placed", "actions to a success (quartiles)",
                   "rollouts from rest: decisions", "groups with mixed outcomes", "paid success",
                   "mixed groups / starts, tasks 0-9"], rows)


def failure_tasks() -> str:
    """Per task, from ``bench_failure_phases``' runs with a ``per_task`` breakdown (:data:`FAILURE_TASK_RUNS`, those
    with the first's episodes): its episodes from rest (success, never grasped, median decisions to a success) and,
    per run, its starts, their groups with mixed outcomes and their paid success."""
    found = _failure_runs(name for name, _ in FAILURE_TASK_RUNS)
    runs = [(found[name], label) for name, label in FAILURE_TASK_RUNS if name in found]
    runs = [(r, label) for r, label in runs if "per_task" in r and r["episode_stages"] == runs[0][0]["episode_stages"]]
    first = runs[0][0]
    header = ["task (the black bowl ...)", "success from rest", "never grasped", "decisions to a success (median)"]
    for r, label in runs:
        header += [f"{r['horizon_decisions']} decisions {label}: starts", "mixed groups", "paid success"]
    rows = []
    for task, t in first["per_task"].items():
        won = t["decisions_to_success"]
        row = [_task_label(task), f"{t['success']:.2f} of {t['episodes']}", str(t["episode_stages"]["never grasped"]),
               "" if won is None else f"{won:g}"]
        for r, _ in runs:
            mine = r["per_task"].get(task)
            row += ["0", "0", ""] if mine is None else [
                str(mine["starts"]), str(mine["mixed_groups"]),
                "" if mine["paid_success"] is None else f"{mine['paid_success']:.3f}"]
        rows.append(row)
    return _table(header, rows)


TABLES: dict[str, Callable[[], str]] = {
    "readme-results": readme_results, "claim1": claim1, "claim2": claim2, "claim3": claim3,
    "proprio-modes": proprio_modes, "reward-labels": reward_labels,
    "reward-detector-on-policy": reward_detector_on_policy, "reward-detector-sizes": reward_detector_sizes,
    "grpo-arms": grpo_arms,
    "mjx-throughput": mjx_throughput, "benchmarks": benchmarks,
    "grpo-refresh-runs": grpo_refresh_runs, "grpo-refresh-replay": grpo_refresh_replay,
    "grpo-refresh-causes": grpo_refresh_causes, "grpo-refresh-policy-data": grpo_refresh_policy_data,
    "grpo-refresh-separation": grpo_refresh_separation,
    "grpo-refresh-3seeds": lambda: grpo_refresh_runs((*THREE_SEEDS, "grpo_refresh_summary.json")),
    "grpo-refresh-3seeds-diagnosis": grpo_refresh_three_seeds_diagnosis,
    "grpo-setting-arms": grpo_setting_arms, "grpo-refresh-probe": grpo_refresh_probe,
    "grpo-reward-source": grpo_reward_source, "policy-view": policy_view, "closed-loop": closed_loop,
    "action-gap": action_gap, "lag-success": lag_success, "closed-loop-sampler": closed_loop_sampler,
    "closed-loop-prev": closed_loop_prev, "policy-view-vae": policy_view_vae, "lag-proprio": lag_proprio,
    "sim-fidelity": sim_fidelity, "sim-fidelity-decisions": sim_fidelity_decisions,
    "grpo-reward-source-rest": grpo_reward_source_rest,
    "grpo-reward-source-levers": grpo_reward_source_levers,
    "grpo-reward-source-length": grpo_reward_source_length,
    "grpo-reward-source-branched": grpo_reward_source_branched, "grpo-reward-source-phases": grpo_reward_source_phases,
    "grpo-first-half-decisions": grpo_first_half_decisions,
    "grpo-first-half-as-trained": grpo_first_half_as_trained,
    "grpo-first-half-world-model": grpo_first_half_world_model,
    "grpo-by-start": grpo_by_start, "grpo-by-start-window": lambda: grpo_by_start(BY_START_WINDOW),
    "grpo-by-start-refresh": lambda: grpo_by_start(BY_START, BY_START_REFRESH),
    "grpo-refresh-fidelity": grpo_refresh_fidelity, "lag-by-start": lag_by_start_table,
    "grpo-by-start-closed-loop": lambda: grpo_by_start(BY_START, BY_START_REFRESH, BY_START_CLOSED_LOOP),
    "grpo-closed-loop-fidelity": lambda: grpo_refresh_fidelity(CLOSED_LOOP_RUNS),
    "grpo-closed-loop-decisions": grpo_closed_loop_decisions,
    "grpo-closed-loop-fit": grpo_closed_loop_fit,
    "lag-by-start-actions": lag_by_start_actions,
    "world-model-heldout": world_model_heldout,
    "world-model-policy-split": world_model_policy_split,
    "world-model-policy-scaling": world_model_policy_scaling,
    "world-model-size": world_model_size,
    "world-model-size-by-start": world_model_size_by_start,
    "world-model-segments": world_model_segments,
    "outcome-determinacy": outcome_determinacy,
    "grpo-reward-source-rest-decisions": lambda: sim_fidelity_decisions((*REWARD_SOURCE_REST, "exec_s0")),
    "failure-tasks": failure_tasks, "failure-rest-horizons": failure_rest_horizons,
    "failure-rest-chunk": failure_rest_chunk,
    "grpo-per-task": grpo_per_task, "grpo-rest-per-task": lambda: grpo_per_task(REST_PER_TASK_RUNS),
    "grpo-rest-cut-vs-whole": grpo_rest_cut_vs_whole,
    "closed-loop-noise": closed_loop_noise,
    "closed-loop-world-models": closed_loop_world_models,
    "closed-loop-world-models-decisions": closed_loop_world_models_decisions,
    "start-latents": start_latents,
    "closed-loop-starts": closed_loop_starts,
    "action-conditioning": action_conditioning,
    "sim-fidelity-fine-tunes": sim_fidelity_fine_tunes, "sim-fidelity-world-model-steps": sim_fidelity_world_model_steps,
    "grpo-horizon-signal": grpo_horizon_signal, "grpo-horizon-honesty": grpo_horizon_honesty,
    "grpo-branched-open": grpo_branched_open,
    "grpo-noise-control": grpo_noise_control,
    "grpo-gradient-signal": grpo_gradient_signal,
    "grpo-branched-value": grpo_branched_value,
    "value-signal": value_signal,
    "failure-stages": failure_stages,
}


def render(text: str) -> str:
    """``text`` with every generated table rebuilt from the JSON; an unknown table name is an error."""
    def block(match: re.Match) -> str:
        name = match.group(2)
        if name not in TABLES:
            raise KeyError(f"unknown generated table {name!r}; known: {', '.join(TABLES)}")
        return f"{match.group(1)}{TABLES[name]()}\n{match.group(4)}"

    return _BLOCK.sub(block, text)


def stale(root: str = ROOT) -> list[str]:
    """The documents (relative paths) whose generated tables differ from what the JSON gives."""
    out = []
    for name in DOCUMENTS:
        with open(os.path.join(root, name)) as f:
            text = f.read()
        if render(text) != text:
            out.append(name)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = cli.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only check; exit 1 if a table disagrees with the JSON")
    args = parser.parse_args(argv)
    if args.check:
        out_of_date = stale()
        if out_of_date:
            raise SystemExit(f"benchmarks.report: generated tables out of date in {', '.join(out_of_date)}; "
                             "run python -m benchmarks.report")
        return 0
    for name in DOCUMENTS:
        path = os.path.join(ROOT, name)
        with open(path) as f:
            text = f.read()
        new = render(text)
        if new != text:
            with open(path, "w") as f:
                f.write(new)
            print(f"rewrote the generated tables of {name}")
    return 0


if __name__ == "__main__":
    cli.run(main)
