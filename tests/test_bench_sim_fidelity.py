"""benchmarks.bench_sim_fidelity: every job's command, GPU and inputs, the run loop with the processes faked, and
the summary of the files a run leaves."""

import dataclasses
import functools
import itertools
import json
import os
import sys
import time

import pytest

from benchmarks import bench_grpo_reward_source as rs
from benchmarks import bench_sim_fidelity as fid
from sword_jax.rl.env_rollout import difference_interval


def _args(tmp_path, *extra, gpus="0,1,2,3", variants="base,vae8x,lpips", decoded=True):
    policy = tmp_path / "p" / "policy_d50.npz"
    policy.parent.mkdir(exist_ok=True)
    policy.touch()
    return fid.parse(["run", "--workdir", str(tmp_path / "w"), "--policy", str(policy), "--gpus", gpus,
                      "--variants", variants, *(["--decoded-sft"] if decoded else []), *extra])


def _config(cmd):
    """The experiment config a command builds (what its VAE loader reads), and the flags left to its parser."""
    import configs

    return configs.from_argv(list(cmd[3:]))


def test_every_command_that_loads_a_vae_builds_its_variants_architecture(tmp_path):
    args = _args(tmp_path, "--exec-steps", "3", "--rollout-batch", "32", "--eval-episodes-per-task", "7",
                 "--view-episodes-per-task", "11", "--sft-steps", "500", "--decoded-fraction", "0.25")
    jobs, work, policy = fid.plan(args), str(tmp_path / "w"), str(tmp_path / "p" / "policy_d50.npz")
    assert sorted(jobs) == sorted([f"{k}_{v}" for k in ("pipeline", "view", "exec") for v in ("base", "vae8x", "lpips")]
                                  + ["policy_dec", "view_base_dec", "exec_base_dec"])
    spatial = {"base": 16, "vae8x": 8, "lpips": 16}
    for variant in fid.VARIANTS:
        pipe = os.path.join(work, f"pipeline_{variant}")
        pipeline, view, ex = (jobs[f"{k}_{variant}"].command for k in ("pipeline", "view", "exec"))
        for cmd in (pipeline, view, ex):
            cfg, _ = _config(cmd)
            assert cfg.vae.spatial_factor == spatial[variant] and cfg.name == "sword-small", (variant, cmd)
            assert cfg.vae.perceptual_weight == (1.0 if variant == "lpips" else 0.0)
            assert [c for c in cmd if c.startswith("--vae.") and "train_steps" not in c] == list(fid.VARIANTS[variant])
        # the pipeline: Sword's small pipeline with the policy's own episodes, in its own folder
        assert pipeline[2:4] == ("train.pipeline", "--config") and pipeline[pipeline.index("--workdir") + 1] == pipe
        assert "--stop-after" in pipeline and pipeline[pipeline.index("--stop-after") + 1] == "reward_model"
        for flag in ("--data.policy_rollouts_per_task=20", f"--rl.sft.init={policy}", "--vae.train_steps=1000",
                     "--trainer.steps=12000"):
            assert flag in pipeline, (flag, pipeline)
        # the view probe: real and round-tripped frames through this variant's VAE, in the simulator's mode
        cfg, rest = _config(view)
        assert view[2] == "benchmarks.bench_policy_view" and cfg.rl.grpo.temperature == 0.5
        assert cfg.rl.imagined.execute_steps == 4
        assert rest == ["--policy", policy, "--views", "real,vae", "--vae", os.path.join(pipe, "vae_run", "vae"),
                        "--episodes-per-task", "11", "--out", os.path.join(work, f"view_{variant}")]
        # the exec arm: bench_grpo_reward_source's recipe in this variant's world model, paid by execution
        for flag in rs.RECIPE + rs.WORLD_MODEL + ("--rl.imagined.reward=executed", "--rl.grpo.steps=3",
                                                  "--rl.grpo.eval_every=100", "--rl.grpo.rollout_batch=32",
                                                  "--rl.grpo.eval_episodes_per_task=7"):
            assert flag in ex, (flag, ex)
        assert ex[2] == "train.grpo" and ex[ex.index("--seed") + 1] == "0" and ex[ex.index("--policy") + 1] == policy
        for flag, path in (("--world-model", "world_model"), ("--vae", "vae_run/vae"), ("--reward", "rl/reward_model"),
                           ("--demos", "data/demos.hdf5")):
            assert ex[ex.index(flag) + 1] == os.path.join(pipe, path)
        assert ex[ex.index("--workdir") + 1] == os.path.join(work, f"exec_{variant}")
    # the decoder-aware policy: fine-tuned from the policy on the base VAE's frames, then measured in that VAE
    sft = jobs["policy_dec"].command
    cfg, rest = _config(sft)
    base_vae = os.path.join(work, "pipeline_base", "vae_run", "vae")
    assert sft[2:4] == ("benchmarks.bench_policy", "sft") and cfg.vae.spatial_factor == 16
    assert cfg.rl.sft.init == policy and cfg.rl.sft.decoded_fraction == 0.25 and cfg.rl.sft.steps == 500
    assert cfg.rl.sft.learning_rate == 3e-4  # a fine-tune's rate, below the 1e-3 the policy was trained at
    assert rest[rest.index("--vae") + 1] == base_vae and rest[rest.index("--out") + 1] == os.path.join(work, "policy_dec")
    assert rest[rest.index("--demos-per-task") + 1] == "50"  # hence policy_d50.npz
    dec = os.path.join(work, "policy_dec", "policy_d50.npz")
    view, ex = jobs["view_base_dec"].command, jobs["exec_base_dec"].command
    assert view[view.index("--policy") + 1] == dec and view[view.index("--vae") + 1] == base_vae
    assert view[view.index("--out") + 1] == os.path.join(work, "view_base_dec")
    assert ex[ex.index("--policy") + 1] == dec and ex[ex.index("--workdir") + 1] == os.path.join(work, "exec_base_dec")
    assert [c for c in ex if c not in (dec, os.path.join(work, "exec_base_dec"))] == [
        c for c in jobs["exec_base"].command if c not in (policy, os.path.join(work, "exec_base"))]


def test_the_fine_tunes_run_in_the_chosen_variant_beside_a_control(tmp_path):
    args = _args(tmp_path, "--decoded-variant", "vae8x", "--sft-control", "--decoded-fraction", "0.25",
                 variants="vae8x")
    jobs, work, policy = fid.plan(args), str(tmp_path / "w"), str(tmp_path / "p" / "policy_d50.npz")
    assert sorted(jobs) == sorted(["pipeline_vae8x", "view_vae8x", "exec_vae8x", "policy_dec", "view_vae8x_dec",
                                   "exec_vae8x_dec", "policy_ctl", "view_vae8x_ctl", "exec_vae8x_ctl"])
    # one GPU each: the pipeline, the decoder-aware fine-tune, the control
    assert [jobs[n].gpu for n in ("pipeline_vae8x", "policy_dec", "policy_ctl")] == ["0", "1", "2"]
    assert jobs["exec_vae8x_ctl"].gpu == jobs["view_vae8x_ctl"].gpu == "2"
    vae = os.path.join(work, "pipeline_vae8x", "vae_run", "vae")
    dec, ctl = jobs["policy_dec"].command, jobs["policy_ctl"].command
    for cmd, fraction in ((dec, 0.25), (ctl, 0.0)):
        cfg, rest = _config(cmd)
        assert cfg.vae.spatial_factor == 8 and cfg.rl.sft.decoded_fraction == fraction and cfg.rl.sft.init == policy
        assert cfg.rl.sft.steps == 1000 and cfg.rl.sft.learning_rate == 3e-4  # the two differ only in the frames
    assert dec[dec.index("--vae") + 1] == vae and "--vae" not in ctl  # the control reads no VAE
    assert ctl[ctl.index("--out") + 1] == os.path.join(work, "policy_ctl")
    needs = {n: {x.path for x in j.needs} for n, j in jobs.items()}
    assert needs["policy_dec"] == {os.path.join(work, "pipeline_vae8x", "stages", "vae.json")}
    assert needs["policy_ctl"] == set()  # it starts at once, its probe once the VAE it reads exists
    assert os.path.join(work, "pipeline_vae8x", "stages", "vae.json") in needs["view_vae8x_ctl"]
    tuned = os.path.join(work, "policy_ctl", "policy_d50.npz")
    view, ex = jobs["view_vae8x_ctl"].command, jobs["exec_vae8x_ctl"].command
    assert view[view.index("--policy") + 1] == tuned and view[view.index("--vae") + 1] == vae
    assert ex[ex.index("--world-model") + 1] == os.path.join(work, "pipeline_vae8x", "world_model")
    assert [c for c in ex if c not in (tuned, os.path.join(work, "exec_vae8x_ctl"))] == [
        c for c in jobs["exec_vae8x"].command if c not in (policy, os.path.join(work, "exec_vae8x"))]
    assert os.path.join(work, "policy_ctl", "sft_results.json") in needs["exec_vae8x_ctl"]
    # the imagined fine-tune: once the world model is built, on the frames it imagines from the demonstrations
    img = fid.plan(_args(tmp_path, "--decoded-variant", "vae8x", "--imagined-sft", "--sft-control",
                         variants="vae8x"))
    assert [img[n].gpu for n in ("pipeline_vae8x", "policy_dec", "policy_img", "policy_ctl")] == ["0", "1", "2", "3"]
    cfg, rest = _config(img["policy_img"].command)
    assert cfg.rl.sft.decoded_source == "world_model" and cfg.rl.sft.decoded_fraction == 0.5
    # the world model run as the exec arm runs it (4 actions a decision, 12 chunks), windows of its 48 actions
    ex_cfg, _ = _config(img["exec_vae8x_img"].command)
    assert (cfg.rl.imagined.execute_steps, cfg.rl.imagined.max_chunks) == (ex_cfg.rl.imagined.execute_steps,
                                                                           ex_cfg.rl.imagined.max_chunks) == (4, 12)
    assert cfg.rl.sft_decoded_window == ex_cfg.rl.sft_decoded_window == 48
    short = fid.plan(_args(tmp_path, "--decoded-variant", "vae8x", "--imagined-sft", "--imagined-window", "8",
                           variants="vae8x"))
    assert _config(short["policy_img"].command)[0].rl.sft_decoded_window == 8
    assert rest[rest.index("--world-model") + 1] == os.path.join(work, "pipeline_vae8x", "world_model")
    assert rest[rest.index("--vae") + 1] == vae and cfg.vae.spatial_factor == 8
    assert {(x.path, x.final) for x in img["policy_img"].needs} == {
        (os.path.join(work, "pipeline_vae8x", "stages", "world_model.json"), True)}
    assert img["exec_vae8x_img"].gpu == "2" and "exec_vae8x_img" in img and "view_vae8x_img" in img
    # the control alone, and too few free GPUs: the last ones
    alone = fid.plan(_args(tmp_path, "--sft-control", decoded=False))
    assert "policy_dec" not in alone and alone["policy_ctl"].gpu == "3" and "exec_base_ctl" in alone
    both = fid.plan(_args(tmp_path, "--sft-control"))
    assert both["policy_dec"].gpu == "3" and both["policy_ctl"].gpu == "2"


def test_bad_arguments_are_refused(tmp_path):
    for extra, message in ((("--variants", "base,vae16x"), "unknown or repeated variant.*vae16x.*base, vae8x, lpips"),
                           (("--variants", "base,base"), "unknown or repeated variant"),
                           (("--gpus", "0,0"), "distinct GPUs"), (("--rollout-batch", "30"), "multiple of 4"),
                           (("--decoded-fraction", "0"), r"\(0, 1\]"), (("--decoded-fraction", "1.5"), r"\(0, 1\]"),
                           (("--exec-steps", "0"), ">= 1"), (("--view-episodes-per-task", "0"), ">= 1"),
                           (("--deadline-s", "-1"), ">= 0"), (("--imagined-window", "-1"), ">= 0"), (("--variants", "vae8x"), "run in the .base. variant.*add it to --variants"),
                           (("--sft-learning-rate", "0"), r"--sft-learning-rate must be in \(0, 1\)"),
                           (("--memory-fraction", "train=0.3"), "--memory-fraction takes.*got 'train=0.3'"),
                           (("--memory-fraction", "exec=0"), "got 'exec=0'"),
                           (("--memory-fraction", "exec=1.2"), "got 'exec=1.2'"),
                           (("--memory-fraction", "exec"), "got 'exec'"),
                           (("--memory-fraction", "exec=x"), "got 'exec=x'"),
                           (("--memory-fraction", "exec=0.3,exec=0.4"), "got 'exec=0.4'")):
        with pytest.raises(SystemExit, match=message):
            _args(tmp_path, *extra)
    with pytest.raises(SystemExit, match="needs --policy"):
        fid.main(["run", "--workdir", str(tmp_path), "--policy", str(tmp_path / "none.npz")])
    assert fid.parse(["summary", "--workdir", str(tmp_path)]).variants == list(fid.VARIANTS)


def test_a_given_memory_fraction_caps_every_job_of_its_kind(tmp_path):
    """On one GPU the shares of everything that can overlap are small; --memory-fraction gives a kind its own cap
    and the other jobs keep theirs."""
    args = _args(tmp_path, "--imagined-sft", "--sft-control", "--decoded-variant", "vae8x", "--memory-fraction",
                 "exec=0.3,view=0.05", gpus="0", variants="vae8x", decoded=False)
    assert args.memory_fraction == {"exec": 0.3, "view": 0.05}
    jobs = fid.plan(args)
    computed, given = fid.memory_fractions(jobs), fid.memory_fractions(jobs, args.memory_fraction)
    assert computed["exec_vae8x"] == 0.2 and computed["pipeline_vae8x"] == 0.385
    for name, job in jobs.items():
        expected = {"exec": 0.3, "view": 0.05}.get(job.share_kind, computed[name])
        assert given[name] == expected, name
    # a job alone on its GPU is capped too where its kind is given, and free where not
    alone = {"pipeline_base": fid.plan(_args(tmp_path, gpus="0", variants="base", decoded=False))["pipeline_base"]}
    assert fid.memory_fractions(alone) == {} and fid.memory_fractions(alone, {"pipeline": 0.5}) == {"pipeline_base": 0.5}


def test_jobs_left_out_are_not_run_and_a_job_others_wait_for_is_refused(tmp_path):
    both = ("--imagined-sft", "--sft-control", "--decoded-variant", "vae8x")
    args = _args(tmp_path, *both, "--leave-out", "exec_vae8x,view_vae8x", gpus="0", variants="vae8x", decoded=False)
    jobs = fid.plan(args)
    assert "exec_vae8x" not in jobs and "view_vae8x" not in jobs
    assert {"pipeline_vae8x", "policy_img", "exec_vae8x_img", "policy_ctl", "exec_vae8x_ctl"} <= set(jobs)
    # what they would have taken goes to the others, and no set that can overlap asks for more than 90%
    full = fid.memory_fractions(fid.plan(_args(tmp_path, *both, gpus="0", variants="vae8x", decoded=False)))
    fractions = fid.memory_fractions(jobs)
    assert fractions["exec_vae8x_img"] > full["exec_vae8x_img"]
    assert all(fractions[k] >= full[k] for k in fractions)
    for names in _overlapping_sets(jobs, "0"):
        assert sum(fractions[n] for n in names) <= 0.9 + 1e-6, names
    for leave, message in (("exec_base", "exec_base: not a job of this run"),
                           ("pipeline_vae8x", "pipeline_vae8x: view_vae8x waits for what it makes"),
                           ("policy_img", "policy_img: (view|exec)_vae8x_img waits for what it makes")):
        with pytest.raises(SystemExit, match=message):
            _args(tmp_path, *both, "--leave-out", leave, gpus="0", variants="vae8x", decoded=False)


def _overlapping_sets(jobs, gpu):
    here = [n for n in jobs if jobs[n].gpu == gpu]
    for r in range(1, len(here) + 1):
        for names in itertools.combinations(here, r):
            if all(fid.can_overlap(jobs, a, b) for a, b in itertools.combinations(names, 2)):
                yield names


def test_jobs_are_placed_and_wait_for_what_they_read(tmp_path):
    jobs = fid.plan(_args(tmp_path))
    gpu = {n: j.gpu for n, j in jobs.items()}
    assert [gpu[f"pipeline_{v}"] for v in ("base", "vae8x", "lpips")] == ["0", "1", "2"]  # one GPU each
    assert all(gpu[f"{k}_{v}"] == gpu[f"pipeline_{v}"] for k in ("view", "exec") for v in fid.VARIANTS)
    assert gpu["policy_dec"] == gpu["view_base_dec"] == gpu["exec_base_dec"] == "3"  # the GPU no pipeline uses
    pipe = str(tmp_path / "w" / "pipeline_base")
    needs = {n: {(x.job, x.path, x.final) for x in j.needs} for n, j in jobs.items()}
    assert needs["view_base"] == {("pipeline_base", f"{pipe}/stages/vae.json", False)}
    # the pipeline runs its stages two at a time: the detector may be done before the world model
    built = {("pipeline_base", f"{pipe}/stages/world_model.json", True),
             ("pipeline_base", f"{pipe}/stages/reward_model.json", True)}
    assert needs["exec_base"] == built
    assert needs["policy_dec"] == needs["view_base"] and not needs["pipeline_vae8x"]
    assert needs["exec_base_dec"] == built | {("policy_dec", str(tmp_path / "w" / "policy_dec" / "sft_results.json"),
                                                True)}
    # the probe starts once the decoded policy is wholly written (its reckoning comes after it)
    assert needs["view_base_dec"] == {("policy_dec", str(tmp_path / "w" / "policy_dec" / "policy_d50.reckoning.json"),
                                       False), ("pipeline_base", str(tmp_path / "w" / "pipeline_base" / "stages" /
                                                                     "vae.json"), False)}
    assert fid.starts_after_end(jobs, "exec_base", "pipeline_base")
    assert not fid.starts_after_end(jobs, "view_base", "pipeline_base")
    assert fid.starts_after_end(jobs, "exec_base_dec", "policy_dec") and fid.can_overlap(jobs, "view_base_dec", "policy_dec")
    fractions = fid.memory_fractions(jobs)
    # beside the pipeline, then beside the exec run; the decoder-aware SFT and its probe likewise
    assert fractions["pipeline_base"] == 0.675 and fractions["view_base"] == 0.225 and fractions["exec_base"] == 0.6
    assert fractions["policy_dec"] == fractions["exec_base_dec"] == 0.6 and fractions["view_base_dec"] == 0.3
    for two in (_args(tmp_path, gpus="0,1"), _args(tmp_path, gpus="4,5,6,7,8"), _args(tmp_path)):
        jobs, fractions = fid.plan(two), fid.memory_fractions(fid.plan(two))
        for g in two.gpus:  # no set of jobs that can run at once on a GPU asks for more than 90% of it
            for names in _overlapping_sets(jobs, g):
                assert sum(fractions[n] for n in names) <= 0.9 + 1e-6, names
    crowded = fid.plan(_args(tmp_path, gpus="0,1"))
    assert [crowded[f"pipeline_{v}"].gpu for v in ("base", "vae8x", "lpips")] == ["0", "1", "0"]
    assert crowded["policy_dec"].gpu == "1"  # none free: the last
    assert fid.plan(_args(tmp_path, gpus="4,5,6,7,8"))["policy_dec"].gpu == "7"
    assert "policy_dec" not in fid.plan(_args(tmp_path, decoded=False))


def _fake(tmp_path, job, writes=(), code=0, sleep=0.0, child=False):
    """A process that records, as it starts, which of its inputs exist and its environment, then sleeps, writes
    ``writes`` in order and exits ``code`` (with ``child``, it first starts a sleeping child and names its pid)."""
    report = str(tmp_path / "seen" / f"{job.name}.json")
    needs = [n.path for n in job.needs if n.path]  # a need without a path is its job's end
    script = (f"import json, os, subprocess, sys, time\n"
              f"json.dump({{'inputs': [os.path.exists(p) for p in {needs!r}], 'gpu': os.environ['CUDA_VISIBLE_DEVICES'],"
              f" 'started': time.time(),"
              f" 'fraction': os.environ.get('XLA_PYTHON_CLIENT_MEM_FRACTION'),"
              f" 'nvls': os.environ.get('NCCL_NVLS_ENABLE')}}, open({report!r}, 'w'))\n"
              + (f"c = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
                 f"open({report + '.child'!r}, 'w').write(str(c.pid))\n" if child else "")
              + f"time.sleep({sleep})\n"
              f"for p in {list(writes)!r}:\n    os.makedirs(os.path.dirname(p), exist_ok=True); open(p, 'w').write('{{}}')\n"
              f"sys.exit({code})\n")
    return dataclasses.replace(job, command=(sys.executable, "-c", script))


def _faked_plan(tmp_path, monkeypatch, behaviour):
    real = fid.plan
    (tmp_path / "seen").mkdir(exist_ok=True)

    def plan(args):
        jobs = real(args)
        made = {}  # each maker writes the files its dependents wait for, in the order they appear
        for job in jobs.values():
            for need in (n for n in job.needs if n.path):
                made.setdefault(need.job, []).append(need.path)
        return {n: _fake(tmp_path, j, **{"writes": sorted(set(made.get(n, [])), key=lambda p: p.endswith("json") and
                                                          "reward_model" in p), **behaviour.get(n, {})})
                for n, j in jobs.items()}

    monkeypatch.setattr(fid, "plan", plan)


def _seen(tmp_path, name):
    return json.loads((tmp_path / "seen" / f"{name}.json").read_text())


def test_jobs_start_once_their_inputs_exist_and_a_failure_skips_only_its_dependents(tmp_path, monkeypatch):
    vae8x = str(tmp_path / "w" / "pipeline_vae8x" / "stages" / "vae.json")
    _faked_plan(tmp_path, monkeypatch, {
        "pipeline_base": {"sleep": 0.3},
        "pipeline_vae8x": {"writes": [vae8x], "code": 1},  # its VAE trained, then it failed
        "pipeline_lpips": {"writes": [], "code": 1}})  # failed before its VAE
    args = _args(tmp_path)
    summary = fid.run(args, poll_s=0.05)
    ran = {"pipeline_base", "view_base", "exec_base", "pipeline_vae8x", "view_vae8x", "pipeline_lpips", "policy_dec",
           "view_base_dec", "exec_base_dec"}
    assert set(summary["exit_codes"]) == ran
    assert summary["failed"] == ["pipeline_lpips", "pipeline_vae8x"]
    assert summary["skipped"] == {
        "exec_vae8x": f"pipeline_vae8x ended without {tmp_path}/w/pipeline_vae8x/stages/world_model.json",
        "view_lpips": f"pipeline_lpips ended without {tmp_path}/w/pipeline_lpips/stages/vae.json",
        "exec_lpips": f"pipeline_lpips ended without {tmp_path}/w/pipeline_lpips/stages/world_model.json"}
    assert summary["stopped_at_deadline"] == [] and summary["not_started"] == []
    fractions = fid.memory_fractions(fid.plan(args))
    for name in ran:  # each saw its inputs as it started, on its GPU, with its share and multicast off
        seen = _seen(tmp_path, name)
        assert all(seen["inputs"]) and seen["gpu"] == fid.plan(args)[name].gpu and seen["nvls"] == "0", name
        assert seen["fraction"] == f"{fractions[name]:.3f}"
        assert (tmp_path / "w" / f"{name}.log").exists()
    # the summary was written, every part the fakes did not make named missing
    written = json.loads((tmp_path / "w" / "sim_fidelity_summary.json").read_text())
    assert set(written["variants"]) == {"base", "vae8x", "lpips"} and written["best_vae_view"] is None
    assert set(written["variants"]["lpips"]["missing"]) == {"vae", "world_model", "view", "exec"}
    monkeypatch.setattr(fid, "run", functools.partial(fid.run, poll_s=0.05))
    with pytest.raises(SystemExit, match=r"failed \['pipeline_lpips'\], skipped \['exec_lpips', 'view_lpips'\]"):
        fid.main(["run", "--workdir", str(tmp_path / "w2"), "--policy", args.policy, "--gpus", "0",
                  "--variants", "lpips"])


def test_a_deadline_stops_every_process_group_still_running(tmp_path, monkeypatch):
    _faked_plan(tmp_path, monkeypatch, {"pipeline_base": {"sleep": 60, "child": True}})
    args = _args(tmp_path, "--deadline-s", "3", variants="base,vae8x", gpus="0,1")
    summary = fid.run(args, poll_s=0.05)
    assert summary["stopped_at_deadline"] == ["pipeline_base"]
    assert summary["not_started"] == ["exec_base", "exec_base_dec", "policy_dec", "view_base", "view_base_dec"]
    assert summary["exit_codes"]["exec_vae8x"] == 0 and summary["failed"] == []
    child = int((tmp_path / "seen" / "pipeline_base.json.child").read_text())

    def state():  # the pipeline's own child: gone, or dead and waiting to be reaped (Z, X)
        try:
            return open(f"/proc/{child}/stat").read().rsplit(")", 1)[1].split()[0]
        except FileNotFoundError:
            return "gone"

    for _ in range(50):  # SIGKILLed: dead within moments
        if state() in ("gone", "Z", "X"):
            break
        time.sleep(0.1)
    assert state() in ("gone", "Z", "X")


def _loop_row(step, paid, error):
    row = {"step": step, "success_rate": paid, "detector_success": 0.5, "detector_agreement": 0.5}
    for k in (1, 2, 3):
        row.update({f"closed_loop_frame_error_{k}": error * k, f"closed_loop_action_gap_{k}": error * k / 10,
                    f"closed_loop_frame_error_vae_{k}": error * k / 2, f"closed_loop_action_gap_vae_{k}": error * k / 20})
    return row


def _write(path, content):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        f.write(content if isinstance(content, str) else json.dumps(content))


def _view(successes, episodes=200):
    def rate(s):
        return {"mean": s / episodes, "successes": s, "episodes": episodes, "ci95": [s / episodes - 0.05, s / episodes + 0.05],
                "per_task": {}, "seconds": 1.0}

    return {"views": {"real": rate(successes[0]), "vae": rate(successes[1])},
            "vae_round_trip": {"frames": 200, "mean_abs_error": {"r": 3.0, "g": 2.0, "b": 1.0, "all": 2.0},
                               "mean_shift": {"r": -1.0, "g": 0.0, "b": 1.0, "all": 0.0}}}


def test_summary_of_designed_files_and_of_missing_parts(tmp_path, monkeypatch, capsys):
    w = str(tmp_path)
    _write(f"{w}/pipeline_base/stages/vae.json", {"stage": "vae", "results": {"steps": 1000, "first_loss": 0.5,
                                                                             "final_loss": 0.04, "path": "x"}})
    _write(f"{w}/pipeline_base/world_model/metrics.jsonl",
           "".join(json.dumps({"step": 100 * i, "loss": 1.0 / i}) + "\n" for i in range(1, 13)))
    _write(f"{w}/view_base/view_results.json", _view((65, 26)))
    _write(f"{w}/exec_base/rl/grpo/train_history.jsonl",
           json.dumps(_loop_row(1, 2 / 256, 0.1)) + "\n" + json.dumps(_loop_row(2, 4 / 256, 0.3)) + "\n")
    _write(f"{w}/exec_base.log", "")
    _write(f"{w}/pipeline_vae8x/stages/vae.json", {"stage": "vae", "results": {"steps": 1000, "final_loss": 0.02}})
    _write(f"{w}/view_vae8x/view_results.json", _view((64, 50)))
    _write(f"{w}/exec_vae8x.log", "eval step 0: MJX success 0.3\n")  # it ended before any step
    _write(f"{w}/policy_dec/sft_results.json", {"runs": [{"eval": {"ens": {"mean": 0.3, "ci95": [0.26, 0.34],
                                                                           "episodes": 500}}}]})
    _write(f"{w}/view_base_dec/view_results.json", _view((60, 40)))
    _write(f"{w}/policy_ctl/sft_results.json", {"runs": [{"eval": {"ens": {"mean": 0.28, "ci95": [0.24, 0.32],
                                                                           "episodes": 500}}}]})
    _write(f"{w}/view_base_ctl/view_results.json", _view((61, 30)))
    summary = fid.summarize(w, rollout_batch=32)  # 256 trajectories a step
    assert sorted(summary["variants"]) == ["base", "vae8x"]  # lpips left nothing
    base, vae8x = summary["variants"]["base"], summary["variants"]["vae8x"]
    assert base["missing"] == {} and base["overrides"] == []
    assert base["vae"] == {"steps": 1000, "first_loss": 0.5, "final_loss": 0.04}
    assert base["world_model"] == {"steps": 1200, "loss": pytest.approx(sum(1.0 / i for i in range(3, 13)) / 10)}
    view = base["view"]
    assert view["real"]["mean"] == pytest.approx(0.325) and view["vae"]["mean"] == pytest.approx(0.13)
    assert view["difference"]["value"] == pytest.approx(-0.195)
    assert view["difference"]["ci95"] == pytest.approx(list(difference_interval(65, 200, 26, 200)))
    assert view["difference"]["ci95"][1] < 0 and view["round_trip_levels"]["mean_abs_error"]["all"] == 2.0
    ex = base["exec"]
    assert ex["paid_success"]["rate"] == pytest.approx(6 / 512) and ex["paid_success"]["of"] == 512
    assert ex["frame_error_first"] == pytest.approx(0.2) and ex["frame_error_last"] == pytest.approx(0.6)
    assert ex["action_gap_first"] == pytest.approx(0.02) and ex["action_gap_last"] == pytest.approx(0.06)
    assert ex["frame_error_vae_first"] == pytest.approx(0.1) and ex["frame_error_vae_last"] == pytest.approx(0.3)
    assert ex["action_gap_vae_first"] == pytest.approx(0.01) and ex["action_gap_vae_last"] == pytest.approx(0.03)
    assert ex["decisions"] == [1, 3] and ex["source"] == "history"
    assert vae8x["vae"]["final_loss"] == 0.02 and vae8x["vae"]["first_loss"] is None
    assert set(vae8x["missing"]) == {"world_model", "exec"} and "exec" not in vae8x
    decoded = summary["decoded"]
    assert decoded["sft"]["mean"] == 0.3 and decoded["view"]["vae"]["mean"] == pytest.approx(0.2)
    assert decoded["missing"] == {"exec": "no history or log"} and decoded["variant"] == "base"
    control = summary["control"]  # the same fine-tune on real frames, found by its runs' names
    assert control["variant"] == "base" and control["sft"]["mean"] == 0.28
    assert control["view"]["vae"]["mean"] == pytest.approx(0.15) and set(control["missing"]) == {"exec"}
    assert summary["best_vae_view"] == {"variant": "vae8x", "success": pytest.approx(0.25)}
    fid.print_summary(summary)
    printed = capsys.readouterr().out
    assert "[sim-fidelity] base: VAE loss 0.0400" in printed and "missing: world_model, exec" in printed
    assert "[sim-fidelity] base_ctl: SFT (ens) 0.280" in printed
    monkeypatch.setattr(fid.common, "device_name", lambda: "cpu")
    entry = fid.results_entries(summary, w, data="d")["policy_sim_fidelity_small"]
    assert entry["value"] == pytest.approx(0.25) and entry["best"] == "vae8x" and set(entry["variants"]) == {"base", "vae8x"}
    assert "round-tripped through the VAE" in entry["unit"]
    assert entry["decoded"]["variant"] == entry["control"]["variant"] == "base"
    recorded = {}
    monkeypatch.setattr(fid.common, "merge_results", recorded.update)
    fid.main(["summary", "--workdir", w, "--rollout-batch", "32", "--out", f"{w}/out", "--record"])
    assert recorded["policy_sim_fidelity_small"]["value"] == pytest.approx(0.25)
    assert recorded["policy_sim_fidelity_small"]["data"] == f"{w}/out.json" and os.path.exists(f"{w}/out.json")
    assert json.loads(open(f"{w}/out.json").read())["variants"]["base"]["exec"]["steps"] == 2
    # nothing run at all: every part missing, nothing to record
    empty = fid.summarize(str(tmp_path / "none"), ["base", "lpips"])
    assert all(set(e["missing"]) == {"vae", "world_model", "view", "exec"} for e in empty["variants"].values())
    assert "decoded" not in empty and empty["best_vae_view"] is None
    with pytest.raises(SystemExit, match="no view probe"):
        fid.results_entries(empty, w, data="d")


def test_exec_runs_at_world_model_checkpoints_run_one_after_another(tmp_path, monkeypatch):
    """--exec-checkpoints: the pipeline keeps those checkpoints; each run reads its own, with its sampler, on the GPU
    no pipeline uses, once its checkpoint and the detector exist and the run before it has ended (however it ended)."""
    given = ("--world-model-steps", "24000", "--exec-checkpoints", "6000,12000:20,24000:20")
    args = _args(tmp_path, *given, gpus="0,1", variants="vae8x", decoded=False)
    assert args.exec_checkpoints == [(6000, 0), (12000, 20), (24000, 20)]
    jobs = fid.plan(args)
    pipe = str(tmp_path / "w" / "pipeline_vae8x")
    assert {"--trainer.steps=24000", "--trainer.checkpoint_every=6000", "--trainer.keep_checkpoints=4"} <= set(
        jobs["pipeline_vae8x"].command)
    names = ["exec_vae8x_at6000", "exec_vae8x_at12000_s20", "exec_vae8x_at24000_s20"]
    assert [n for n in jobs if "_at" in n] == names and {jobs[n].gpu for n in names} == {"1"}
    needs = {n: {(x.job, x.path, x.final) for x in jobs[n].needs} for n in names}
    detector = ("pipeline_vae8x", f"{pipe}/stages/reward_model.json", False)
    assert needs[names[0]] == {("pipeline_vae8x", f"{pipe}/world_model/checkpoints/6000", False), detector}
    assert needs[names[1]] == {("pipeline_vae8x", f"{pipe}/world_model/checkpoints/12000", False), detector,
                               (names[0], "", True)}
    built = {("pipeline_vae8x", f"{pipe}/stages/{name}.json", True) for name in ("world_model", "reward_model")}
    assert needs[names[2]] == built | {(names[1], "", True)}  # the last step: once the pipeline is built
    for name, step, sampler in zip(names, (6000, 12000, 24000), (5, 20, 20)):
        command = jobs[name].command
        assert command[command.index("--world-model") + 1] == f"{pipe}/world_model/checkpoints/{step}"
        cfg, _ = _config(command)
        assert cfg.flow.sample_steps == sampler and cfg.vae.dim_mult == (1, 4, 4)
    assert fid.can_overlap(jobs, names[0], "pipeline_vae8x") and fid.starts_after_end(jobs, names[1], names[0])
    assert all(fid.memory_fractions(jobs)[n] == 0.9 for n in names)  # never two at once on GPU 1
    assert {fid.plan(_args(tmp_path, *given, gpus="0", variants="vae8x", decoded=False))[n].gpu for n in names} == {"0"}
    # one left out: the next runs without waiting for it
    kept = fid.plan(_args(tmp_path, *given, "--leave-out", names[0], gpus="0,1", variants="vae8x", decoded=False))
    assert names[0] not in kept and all(n.path for n in kept[names[1]].needs)
    for bad, message in (("6000:0", "got '6000:0'"), ("25000", "got '25000'"), ("x", "got 'x'"), ("0", "got '0'"),
                         ("6000,6000", "got '6000'"), ("6000:51", "got '6000:51'"),
                         ("500,24000:20", "every 500 steps, more than 8")):
        with pytest.raises(SystemExit, match=message):
            _args(tmp_path, "--world-model-steps", "24000", "--exec-checkpoints", bad, variants="vae8x", decoded=False)
    # the run loop: the first fails after a while; the second still runs, after it, and the third after the second
    _faked_plan(tmp_path, monkeypatch, {names[0]: {"sleep": 0.5, "code": 1}})
    summary = fid.run(args, poll_s=0.05)
    assert summary["failed"] == [names[0]] and summary["skipped"] == {} and set(names) <= set(summary["exit_codes"])
    first, second, third = (_seen(tmp_path, n) for n in names)
    assert second["started"] >= first["started"] + 0.5 and third["started"] > second["started"]
    assert all(_seen(tmp_path, n)["inputs"] for n in names) and first["gpu"] == "1"


def test_summary_of_exec_runs_at_world_model_checkpoints(tmp_path, capsys):
    w = str(tmp_path)
    _write(f"{w}/pipeline_base/world_model/metrics.jsonl",
           "".join(json.dumps({"step": 500 * i, "loss": 1.0 / i}) + "\n" for i in range(1, 49)))
    for name, error in (("exec_base_at6000", 0.2), ("exec_base_at24000_s20", 0.1)):
        _write(f"{w}/{name}/rl/grpo/train_history.jsonl", json.dumps(_loop_row(1, 8 / 256, error)) + "\n")
        _write(f"{w}/{name}.log", "")
    _write(f"{w}/exec_base_at12000.log", "eval step 0: MJX success 0.3\n")  # ended before its step
    _write(f"{w}/exec_base_atx.log", "")  # not a checkpoint run
    summary = fid.summarize(w, rollout_batch=32)
    runs = summary["variants"]["base"]["checkpoints"]
    assert list(runs) == ["exec_base_at6000", "exec_base_at12000", "exec_base_at24000_s20"]
    at6000, at24000 = runs["exec_base_at6000"], runs["exec_base_at24000_s20"]
    assert (at6000["step"], at6000["sample_steps"], at24000["step"], at24000["sample_steps"]) == (6000, None, 24000, 20)
    # the world model's loss to the checkpoint the run read: the last 10 logged steps to 6000
    assert at6000["exec"]["world_model_steps"] == 6000
    assert at6000["exec"]["world_model_loss"] == pytest.approx(sum(1.0 / i for i in range(3, 13)) / 10)
    assert at24000["exec"]["world_model_steps"] == 24000 and at24000["exec"]["frame_error_first"] == pytest.approx(0.1)
    assert at6000["exec"]["paid_success"]["rate"] == pytest.approx(8 / 256) and at6000["exec"]["detector_success"] == 0.5
    assert "holds no step with the closed-loop record" in runs["exec_base_at12000"]["exec"]
    fid.print_summary(summary)
    printed = capsys.readouterr().out
    assert "[sim-fidelity] exec_base_at6000 (world model at step 6000): paid 0.031" in printed
    assert "exec_base_at24000_s20 (world model at step 24000, 20 sampler steps): paid" in printed
    assert "exec_base_at12000 (world model at step 12000): missing:" in printed
