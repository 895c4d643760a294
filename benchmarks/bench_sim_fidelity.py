"""Which VAE lets the policy read the learned simulator's frames: its success on frames round-tripped through
each VAE variant, and what its actions chosen in each variant's world model earn in reality.

The policy succeeds far less often on frames round-tripped through the pipeline's VAE than on the real ones, and
its actions chosen on the world model's frames rarely succeed in reality (``bench_policy_view --views real,vae``;
the ``exec`` arm of :mod:`benchmarks.bench_grpo_reward_source`). This benchmark trains Sword's ``small`` pipeline
(through the reward model, with ``--policy``'s own episodes in the data) once per VAE variant (:data:`VARIANTS`:
``base``; ``vae8x``, an 8x spatial VAE with 16x16 latents at 128 px; ``lpips``, a VAE trained with LPIPS beside
its pixel loss) and measures, per variant:

* ``view_<variant>``: the policy's success on MJX on real frames and on frames round-tripped through that VAE
  (:mod:`benchmarks.bench_policy_view`, sampled at T 0.5, 4 actions a decision), the difference with its 95%
  interval, and how far the round trip moves the start frames (0-255 levels);
* ``exec_<variant>``: GRPO in that variant's world model paid by the real outcome of its imagined actions
  (:mod:`benchmarks.bench_grpo_reward_source`'s recipe, ``rl.imagined.reward=executed``), for its closed-loop
  record: what its trajectories were paid, and per decision the frame error and greedy action gap against
  reality, with the VAE alone's share where logged.

With ``--decoded-sft`` the policy is also fine-tuned on frames of which ``--decoded-fraction`` went through the
``--decoded-variant`` VAE (``base`` by default; ``bench_policy sft``, ``rl.sft.decoded_fraction``), and that
decoder-aware policy is measured the same way in that variant's VAE and world model (``view_<variant>_dec``,
``exec_<variant>_dec``). ``--imagined-sft`` fine-tunes it alike on the frames that variant's world model shows when
the demonstrations' actions are replayed in it from their real frames (``rl.sft.decoded_source=world_model``; the
world model run as the ``exec`` arm runs it, :data:`IMAGINED`, in windows of its imagined rollout's 48 actions or
``--imagined-window``; ``policy_img``, ``view_<variant>_img``, ``exec_<variant>_img``), once the world model is
built. ``--sft-control`` adds the same fine-tune (steps, rate, data) on real frames only (``policy_ctl``,
``view_<variant>_ctl``, ``exec_<variant>_ctl``), so that what the decoded frames change is told apart from what more
training changes::

    python -m benchmarks.bench_sim_fidelity run --workdir runs/fid --policy runs/p/policy_d50.npz \\
        --gpus 0,1,2,3 --variants base,vae8x,lpips --decoded-sft --vae-steps 1000 --world-model-steps 6000 \\
        --exec-steps 1 --rollout-batch 64 --view-episodes-per-task 20 --eval-episodes-per-task 10 \\
        --sft-steps 1000 --decoded-fraction 0.5 --deadline-s 1380
    python -m benchmarks.bench_sim_fidelity summary --workdir runs/fid \\
        --out benchmarks/results/policy/sim_fidelity_small [--record]

``--exec-checkpoints STEP[:K],...`` asks whether the world model's training is what its closed loop lacks: the
pipeline keeps its checkpoints at those steps (it saves one every greatest common divisor of them and
``--world-model-steps``, all kept), and the starting policy gets an ``exec`` run in each (``exec_<variant>_at<STEP>``,
``_s<K>`` where sampled with K flow steps, ``flow.sample_steps``). They run one after another; on one GPU, list the
last step too and leave out ``exec_<variant>`` (the same run, which would overlap them)::

    python -m benchmarks.bench_sim_fidelity run --workdir runs/fidwm --policy runs/p/policy_d50.npz --gpus 0 \\
        --variants vae8x --world-model-steps 18000 --exec-checkpoints 6000,18000,18000:20 \\
        --leave-out view_vae8x,exec_vae8x --vae-steps 1000 --exec-steps 1 --rollout-batch 64 \\
        --eval-episodes-per-task 2 --deadline-s 1500

``run`` places variant i's pipeline on GPU ``i mod n``; its view probe starts there once its VAE is trained
(``stages/vae.json``) and its ``exec`` run once the pipeline is built (``stages/world_model.json`` and
``stages/reward_model.json``: the pipeline runs its stages two at a time, so either may end last). The
fine-tunes take the GPUs no pipeline uses, in order (where too few are free, the others from the last back): the
decoder-aware one once its variant's VAE exists, the imagined one once its world model does, the control at once;
each one's probe follows it there once the variant's VAE exists too, and its ``exec`` run once the pipeline is built.
The runs at checkpoints take the first of those GPUs, one after another, each once its checkpoint and the detector
exist.
``--memory-fraction`` sets a kind's cap instead (below); ``--leave-out`` drops jobs no other job waits for (on one
GPU, ``exec_<variant>`` when only the fine-tunes are compared). A job whose input can no longer appear (its maker
ended without it) is skipped and the others go on. Each process runs in its own session with its log in ``<workdir>/<job>.log``; a
deadline stops the whole process groups still going. On a shared GPU each process is capped
(``XLA_PYTHON_CLIENT_MEM_FRACTION``, :func:`memory_fractions`): 90% of the GPU is split in proportion to
:data:`WEIGHTS` among the jobs that can run there at once, so no set of jobs that can overlap asks for more than
90%. The world model's training weighs most; a pipeline counts once though its stages run two at a time, the one
beside the world model being the small success detector (each stage process gets the pipeline's cap).

``summary`` (also written by ``run``, to ``<workdir>/sim_fidelity_summary.json``) gives each variant's VAE and
world-model losses, its view figures and its closed-loop record (``--rollout-batch`` x 8 trajectories a step, as
run); parts a run did not leave are named missing. ``--record`` writes ``policy_sim_fidelity_small`` to
``benchmarks/results/latest.json``: the best success on round-tripped frames, beside every variant's figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Sequence

from benchmarks import common
from benchmarks.bench_grpo_refresh import pipeline_command, stop_all
from benchmarks.bench_grpo_reward_source import (RECIPE, VAE_VARIANTS, WORLD_MODEL, closed_loop_summary, pipeline,
                                                 world_model_loss)
from sword_jax import cli
from sword_jax.pipeline.launch import NO_MULTICAST

VARIANTS = VAE_VARIANTS  # variant -> the config overrides of its VAE (bench_grpo_reward_source.VAE_VARIANTS)
VIEW_FLAGS = ("--rl.grpo.temperature=0.5", "--rl.imagined.execute_steps=4")  # the learned simulator's mode
# the fine-tuned policies: kind -> (its SFT job and folder, the suffix of its runs view_<variant>_<suffix>,
# exec_<variant>_<suffix>); "decoded" reads --decoded-fraction of its frames through the VAE, "imagined" as the world
# model imagines them (rl.sft.decoded_source=world_model), "control" none
FINE_TUNES = {"decoded": ("policy_dec", "dec"), "imagined": ("policy_img", "img"), "control": ("policy_ctl", "ctl")}
SFT_POLICY = "policy_d50.npz"  # bench_policy sft --demos-per-task 50, no --tag
# a job's share of a GPU by kind: the world model's training, GRPO in a world model, the decoder-aware SFT, a probe
WEIGHTS = {"pipeline": 3.0, "exec": 2.0, "policy": 2.0, "view": 1.0}
GPU_SHARE = 0.9
GROUP_SIZE = 8  # RECIPE's --rl.grpo.group_size
IMAGINED = tuple(f for f in RECIPE if f.startswith("--rl.imagined."))  # the exec arm's imagined rollout


@dataclasses.dataclass(frozen=True)
class Need:
    """A file a job waits for: ``job`` writes it, ``final`` as that job ends (so the two never overlap). An empty
    ``path`` waits for ``job`` to end, however it ends (or for it to be skipped or left out): jobs run one after
    another on a GPU so that neither slows the other (and, with a persistent compilation cache, the later one finds the
    programs the earlier one compiled)."""
    job: str
    path: str
    final: bool


@dataclasses.dataclass(frozen=True)
class Job:
    """One process of the run: its command, its GPU and the files it starts after."""
    name: str
    command: tuple[str, ...]
    gpu: str
    needs: tuple[Need, ...] = ()

    @property
    def share_kind(self) -> str:
        """Its kind: the key of :data:`WEIGHTS` its name starts with."""
        return self.name.split("_")[0]

    @property
    def share(self) -> float:
        """Its weight (:data:`WEIGHTS`, by its kind)."""
        return WEIGHTS[self.share_kind]


def pipe_dir(workdir: str, variant: str) -> str:
    return os.path.join(workdir, f"pipeline_{variant}")


def vae_dir(workdir: str, variant: str) -> str:
    return os.path.join(pipe_dir(workdir, variant), "vae_run", "vae")


def sft_policy(workdir: str, kind: str = "decoded") -> str:
    return os.path.join(workdir, FINE_TUNES[kind][0], SFT_POLICY)


def tuned_runs(variant: str, kind: str) -> str:
    """The name the runs of fine-tune ``kind`` in ``variant`` carry after ``view_`` and ``exec_``."""
    return f"{variant}_{FINE_TUNES[kind][1]}"


def view_command(args, variant: str, policy: str, out: str) -> tuple[str, ...]:
    return (sys.executable, "-m", "benchmarks.bench_policy_view", "--config", args.config, *VARIANTS[variant],
            "--policy", policy, "--views", "real,vae", "--vae", vae_dir(args.workdir, variant),
            "--episodes-per-task", str(args.view_episodes_per_task), "--out", out, *VIEW_FLAGS)


def exec_command(args, variant: str, policy: str, name: str, *, step: int = 0,
                 sample_steps: int = 0) -> tuple[str, ...]:
    """``train.grpo`` in ``variant``'s world model paid by execution (bench_grpo_reward_source's ``exec`` arm): its
    newest checkpoint, or checkpoint ``step``; the world model's sampler at its config's steps or ``sample_steps``."""
    pipe = pipe_dir(args.workdir, variant)
    world_model = os.path.join(pipe, "world_model", *(("checkpoints", str(step)) if step else ()))
    return (sys.executable, "-m", "train.grpo", "--config", args.config, *VARIANTS[variant],
            *([f"--flow.sample_steps={sample_steps}"] if sample_steps else []), "--simulator",
            "world_model", "--world-model", world_model, "--vae", vae_dir(args.workdir, variant),
            "--reward", os.path.join(pipe, "rl", "reward_model"), "--demos", os.path.join(pipe, "data", "demos.hdf5"),
            "--policy", policy, "--seed", "0", "--workdir", os.path.join(args.workdir, name), *RECIPE, *WORLD_MODEL,
            f"--rl.grpo.eval_episodes_per_task={args.eval_episodes_per_task}", "--rl.imagined.reward=executed",
            f"--rl.grpo.rollout_batch={args.rollout_batch}", f"--rl.grpo.steps={args.exec_steps}",
            "--rl.grpo.eval_every=100")


def sft_command(args, kind: str = "decoded") -> tuple[str, ...]:
    """``bench_policy sft``: the policy fine-tuned with ``--decoded-fraction`` of its frames through the
    ``--decoded-variant`` VAE (``decoded``) or imagined by that variant's world model (``imagined``), or the same
    fine-tune on real frames only (``control``)."""
    variant = args.decoded_variant
    decoded = ((f"--rl.sft.decoded_fraction={args.decoded_fraction}", "--vae", vae_dir(args.workdir, variant))
               if kind != "control" else ("--rl.sft.decoded_fraction=0",))
    if kind == "imagined":  # the world model run as the exec arm runs it: its actions per decision and chunks
        decoded += ("--rl.sft.decoded_source=world_model", "--world-model",
                    os.path.join(pipe_dir(args.workdir, variant), "world_model"), *IMAGINED,
                    f"--rl.sft.decoded_window={args.imagined_window}")
    return (sys.executable, "-m", "benchmarks.bench_policy", "sft", "--config", args.config, *VARIANTS[variant],
            "--out", os.path.join(args.workdir, FINE_TUNES[kind][0]), "--demos-per-task", "50", "--execute", "ens",
            "--workers", "14", "--eval-episodes", "50", "--gen-procs-per-task", "4",
            f"--rl.sft.init={os.path.abspath(args.policy)}", f"--rl.sft.steps={args.sft_steps}",
            f"--rl.sft.learning_rate={args.sft_learning_rate}", *decoded)


def fine_tunes(args) -> list[str]:
    """The fine-tunes the run makes: ``decoded`` with ``--decoded-sft``, ``imagined`` with ``--imagined-sft``, then
    ``control`` with ``--sft-control``."""
    return (["decoded"] * bool(args.decoded_sft) + ["imagined"] * bool(args.imagined_sft)
            + ["control"] * bool(args.sft_control))


def free_gpus(args) -> list[str]:
    """The GPUs in the order the jobs that are not a variant's own take them: those no variant's pipeline uses,
    first to last, then the others from the last back."""
    used = {args.gpus[i % len(args.gpus)] for i in range(len(args.variants))}
    return [g for g in args.gpus if g not in used] + [g for g in reversed(args.gpus) if g in used]


def sft_gpu(args, kind: str = "decoded") -> str:
    """A fine-tune's GPU, one per fine-tune (:func:`fine_tunes`) in :func:`free_gpus`' order."""
    order = free_gpus(args)
    return order[fine_tunes(args).index(kind) % len(order)]


# the stages a pipeline's exec run reads, the last two it builds; with --parallel 2 either may end last
BUILT = ("world_model.json", "reward_model.json")


def built(variant_job: str, pipe: str) -> tuple[Need, ...]:
    """The files that say pipeline ``variant_job`` is built: its world model's and detector's stage records."""
    return tuple(Need(variant_job, os.path.join(pipe, "stages", name), True) for name in BUILT)


def checkpoint_run(variant: str, step: int, sample_steps: int = 0) -> str:
    """The name of the ``exec`` run in ``variant``'s world model at checkpoint ``step`` (sampled with
    ``sample_steps``; 0: the config's)."""
    return f"exec_{variant}_at{step}" + (f"_s{sample_steps}" if sample_steps else "")


def checkpoint_flags(args) -> tuple[str, ...]:
    """The pipeline's trainer flags that keep the world-model checkpoints ``--exec-checkpoints`` reads: a checkpoint
    every greatest common divisor of their steps and the last step, all of them kept."""
    if not args.exec_checkpoints:
        return ()
    every = checkpoint_period(args.exec_checkpoints, args.world_model_steps)
    return (f"--trainer.checkpoint_every={every}", f"--trainer.keep_checkpoints={args.world_model_steps // every}")


def checkpoint_period(checkpoints: Sequence[tuple[int, int]], world_model_steps: int) -> int:
    """The steps between the pipeline's world-model checkpoints that keep every one of ``checkpoints`` and the last."""
    return math.gcd(world_model_steps, *(step for step, _ in checkpoints))


def checkpoint_jobs(args, variant: str, gpu: str) -> list[Job]:
    """The ``exec`` runs of the starting policy at ``--exec-checkpoints`` in ``variant``'s world model, one after
    another on ``gpu`` in the order given; each starts once its checkpoint is saved (the last step: once the
    pipeline is built) and the detector is trained."""
    pipe, policy, jobs = pipe_dir(args.workdir, variant), os.path.abspath(args.policy), []
    for step, sample_steps in args.exec_checkpoints:
        name = checkpoint_run(variant, step, sample_steps)
        ready = (built(f"pipeline_{variant}", pipe) if step == args.world_model_steps else (
            Need(f"pipeline_{variant}", os.path.join(pipe, "world_model", "checkpoints", str(step)), False),
            Need(f"pipeline_{variant}", os.path.join(pipe, "stages", "reward_model.json"), False)))
        after = (Need(jobs[-1].name, "", True),) if jobs else ()
        jobs.append(Job(name, exec_command(args, variant, policy, name, step=step, sample_steps=sample_steps), gpu,
                        ready + after))
    return jobs


def plan(args) -> dict[str, Job]:
    """Every job of the run (module docstring), in launch order where several are ready at once."""
    policy = os.path.abspath(args.policy)
    jobs = []
    for i, variant in enumerate(args.variants):
        gpu, pipe = args.gpus[i % len(args.gpus)], pipe_dir(args.workdir, variant)
        vae_done = Need(f"pipeline_{variant}", os.path.join(pipe, "stages", "vae.json"), False)
        command = pipeline_command(pipeline(args), VARIANTS[variant], name=f"pipeline_{variant}",
                                   own=checkpoint_flags(args))
        view = view_command(args, variant, policy, os.path.join(args.workdir, f"view_{variant}"))
        jobs += [Job(f"pipeline_{variant}", tuple(command), gpu),
                 Job(f"view_{variant}", view, gpu, (vae_done,)),
                 Job(f"exec_{variant}", exec_command(args, variant, policy, f"exec_{variant}"), gpu,
                     built(f"pipeline_{variant}", pipe))]
        jobs += checkpoint_jobs(args, variant, free_gpus(args)[i % len(args.gpus)])
    variant = args.decoded_variant
    pipe = pipe_dir(args.workdir, variant)
    for kind in fine_tunes(args):
        gpu, tuned, sft, runs = sft_gpu(args, kind), sft_policy(args.workdir, kind), FINE_TUNES[kind][0], tuned_runs(variant, kind)
        saved = Need(sft, os.path.splitext(tuned)[0] + ".reckoning.json", False)  # written after the policy
        # the decoder-aware fine-tune reads the VAE, the imagined one the world model too; the control starts at once
        needs = {"decoded": (Need(f"pipeline_{variant}", os.path.join(pipe, "stages", "vae.json"), False),),
                 "imagined": (Need(f"pipeline_{variant}", os.path.join(pipe, "stages", "world_model.json"), True),),
                 "control": ()}[kind]
        view = view_command(args, variant, tuned, os.path.join(args.workdir, f"view_{runs}"))
        vae_done = Need(f"pipeline_{variant}", os.path.join(pipe, "stages", "vae.json"), False)
        jobs += [Job(sft, sft_command(args, kind), gpu, needs),
                 Job(f"view_{runs}", view, gpu, (saved, vae_done)),  # the probe reads the VAE too
                 Job(f"exec_{runs}", exec_command(args, variant, tuned, f"exec_{runs}"), gpu,
                     (*built(f"pipeline_{variant}", pipe), Need(sft, os.path.join(args.workdir, sft, "sft_results.json"), True)))]
    return left_out({job.name: job for job in jobs}, args.leave_out)


def left_out(jobs: dict[str, Job], names: Sequence[str]) -> dict[str, Job]:
    """``jobs`` without ``names`` (``--leave-out``), refused by name where one is not a job of the run or another
    job waits for a file it makes."""
    unknown = [n for n in names if n not in jobs]
    if unknown:
        raise SystemExit(f"bench_sim_fidelity: --leave-out {', '.join(unknown)}: not a job of this run; its jobs are "
                         f"{', '.join(jobs)}")
    kept = {n: dataclasses.replace(j, needs=tuple(need for need in j.needs if need.path or need.job not in names))
            for n, j in jobs.items() if n not in names}  # one run after another: the later runs without the earlier
    for name, job in kept.items():
        needed = sorted({need.job for need in job.needs} & set(names))
        if needed:
            raise SystemExit(f"bench_sim_fidelity: --leave-out {', '.join(needed)}: {name} waits for what it makes")
    return kept


def starts_after_end(jobs: dict[str, Job], later: str, earlier: str) -> bool:
    """Whether job ``later`` can start only after job ``earlier`` has ended (it needs a file ``earlier`` writes as
    it ends, or one of a job that starts only then)."""
    return any((n.job == earlier and n.final) or (n.job in jobs and starts_after_end(jobs, n.job, earlier))
               for n in jobs[later].needs)


def can_overlap(jobs: dict[str, Job], a: str, b: str) -> bool:
    """Whether jobs ``a`` and ``b`` can run at the same time (neither starts only after the other's end)."""
    return not (starts_after_end(jobs, a, b) or starts_after_end(jobs, b, a))


def memory_fractions(jobs: dict[str, Job], given: dict[str, float] | None = None) -> dict[str, float]:
    """``XLA_PYTHON_CLIENT_MEM_FRACTION`` of each process of the jobs that share a GPU with another: 90% of it times
    the job's weight over the largest total weight of jobs that can run there at once with it (none follows
    another's end), so no such set asks for more than 90% together. ``given`` (kind -> fraction, the kinds of
    :data:`WEIGHTS`) sets every job of a kind its cap instead, alone on its GPU or not: a cap is the most a process
    may take (none takes memory before it needs it), so jobs known not to run at once can be given more."""
    given = given or {}
    out = {name: given[job.share_kind] for name, job in jobs.items() if job.share_kind in given}
    for gpu in dict.fromkeys(j.gpu for j in jobs.values()):
        here = [n for n in jobs if jobs[n].gpu == gpu]
        if len(here) < 2:
            continue
        together = [c for r in range(1, len(here) + 1) for c in itertools.combinations(here, r)
                    if all(can_overlap(jobs, a, b) for a, b in itertools.combinations(c, 2))]
        for name in (n for n in here if n not in out):
            most = max(sum(jobs[n].share for n in c) for c in together if name in c)
            out[name] = math.floor(1000 * GPU_SHARE * jobs[name].share / most) / 1000  # rounded down: never above
    return out


def blocked_by(job: Job, procs: dict[str, subprocess.Popen], skipped: dict[str, str]) -> Need | None:
    """The needed file ``job`` can no longer get (its maker was skipped, or ended without it), if any."""
    for need in (n for n in job.needs if n.path):
        ended = need.job in skipped or (need.job in procs and procs[need.job].poll() is not None)  # before the file
        if ended and not os.path.exists(need.path):
            return need
    return None


def met(need: Need, procs: dict[str, subprocess.Popen], skipped: dict[str, str]) -> bool:
    """Whether ``need`` is there: its file, or (no path) its job's end."""
    if need.path:
        return os.path.exists(need.path)
    return need.job in skipped or (need.job in procs and procs[need.job].poll() is not None)


def run(args, *, poll_s: float = 5.0) -> dict:
    """Every job as its inputs appear (module docstring); the summary at the end."""
    os.makedirs(args.workdir, exist_ok=True)
    common.record_gpus(os.path.join(args.workdir, "gpu.txt"))
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false", PYTHONUNBUFFERED="1", **NO_MULTICAST)
    jobs = plan(args)
    fractions = memory_fractions(jobs, args.memory_fraction)
    start = time.perf_counter()

    def launch(job: Job) -> subprocess.Popen:
        own = dict(env, CUDA_VISIBLE_DEVICES=job.gpu)
        if job.name in fractions:
            own["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{fractions[job.name]:.3f}"
        print(f"[sim-fidelity] {job.name} on GPU {job.gpu} (memory fraction {fractions.get(job.name, 'free')}, "
              f"{time.perf_counter() - start:.0f} s): {' '.join(job.command[2:])}", flush=True)
        with open(os.path.join(args.workdir, f"{job.name}.log"), "a") as log:
            return subprocess.Popen(list(job.command), stdout=log, stderr=subprocess.STDOUT, env=own,
                                    start_new_session=True)

    pending, procs, skipped, stopped = dict(jobs), {}, {}, []
    while pending or any(p.poll() is None for p in procs.values()):
        for name, job in list(pending.items()):
            lost = blocked_by(job, procs, skipped)
            if lost:
                skipped[name] = f"{lost.job} ended without {lost.path}"
                print(f"[sim-fidelity] {name} skipped: {skipped[name]} (log: {args.workdir}/{lost.job}.log)", flush=True)
            elif all(met(n, procs, skipped) for n in job.needs):
                procs[name] = launch(job)
            else:
                continue
            del pending[name]
        if args.deadline_s and time.perf_counter() - start > args.deadline_s:
            running = stop_all(list(procs.values()))
            stopped = sorted(n for n, p in procs.items() if any(p is r for r in running))
            print(f"[sim-fidelity] deadline of {args.deadline_s:.0f} s: stopped {stopped}, never started "
                  f"{sorted(pending)}", flush=True)
            break
        time.sleep(poll_s)
    summary = dict(summarize(args.workdir, args.variants, rollout_batch=args.rollout_batch),
                   exit_codes={n: p.returncode for n, p in procs.items()}, skipped=skipped,
                   stopped_at_deadline=stopped, not_started=sorted(pending), memory_fractions=fractions,
                   seconds=round(time.perf_counter() - start, 1))
    summary["failed"] = sorted(n for n, p in procs.items() if p.returncode and n not in stopped)
    with open(os.path.join(args.workdir, "sim_fidelity_summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    return summary


def _read_json(path: str) -> dict | None:
    if not os.path.exists(path):
        return None
    with open(path) as f:
        return json.load(f)


def view_summary(path: str) -> dict | None:
    """The policy's real and VAE-view success with intervals, the difference (vae - real) with its 95% interval,
    and the round trip's error on the start frames in 0-255 levels."""
    from sword_jax.rl.env_rollout import difference_interval

    results = _read_json(os.path.join(path, "view_results.json"))
    if results is None:
        return None
    views = results["views"]
    out = {v: {k: views[v][k] for k in ("mean", "ci95", "successes", "episodes")} for v in ("real", "vae") if v in views}
    if len(out) == 2:
        real, vae = out["real"], out["vae"]
        out["difference"] = {"value": vae["mean"] - real["mean"], "ci95": list(difference_interval(
            real["successes"], real["episodes"], vae["successes"], vae["episodes"]))}
    if "vae_round_trip" in results:
        trip = results["vae_round_trip"]
        out["round_trip_levels"] = {"mean_abs_error": trip["mean_abs_error"], "mean_shift": trip["mean_shift"]}
    return out


def exec_summary(workdir: str, name: str, variant: str, rollout_batch: int, step: int | None = None) -> dict | str:
    """:func:`~benchmarks.bench_grpo_reward_source.closed_loop_summary` of run ``name`` (in the world model's
    checkpoint ``step`` where given): paid success, the detector's success on the same trajectories, the first and
    last decisions' frame error and greedy action gap, the VAE alone's where logged, the world model's loss to its
    step; or why it is missing."""
    grpo, metrics = os.path.join(workdir, name, "rl", "grpo"), os.path.join(pipe_dir(workdir, variant), "world_model",
                                                                           "metrics.jsonl")
    log = os.path.join(workdir, f"{name}.log")
    if not os.path.exists(os.path.join(grpo, "train_history.jsonl")) and not os.path.exists(log):
        return "no history or log"
    if not os.path.exists(metrics):
        return f"no world-model metrics at {metrics}"
    try:
        run = closed_loop_summary([(name, grpo, log, metrics, *([step] if step else []))],
                                  rollout_batch * GROUP_SIZE)[name]
    except SystemExit as err:
        return str(err)
    out = {k: run[k] for k in ("steps", "source", "paid_success", "detector_success", "world_model_steps",
                               "world_model_loss", "frame_error_first", "frame_error_last",
                               "action_gap_first", "action_gap_last", "frame_error_vae_first", "action_gap_vae_first")
           if k in run}
    loop = run.get("per_decision", {})
    if loop:
        out["decisions"] = [loop["decisions"][0], loop["decisions"][-1]]
        out.update({f"{what}_last": loop[what][-1] for what in ("frame_error_vae", "action_gap_vae") if what in loop})
    return out


def summarize(workdir: str, variants: Sequence[str] = (), *, rollout_batch: int = 64) -> dict:
    """Per variant (those given, else those with a pipeline, probe or run under ``workdir``) its VAE's training
    loss, its world model's loss, the view probe and the ``exec`` run's closed loop; likewise the decoder-aware
    policy where there is one. Parts not there are named in ``missing``."""
    variants = list(variants) or [v for v in VARIANTS if any(
        os.path.exists(os.path.join(workdir, f"{kind}_{v}")) for kind in ("pipeline", "view", "exec"))]
    out: dict = {"variants": {}}
    for variant in variants:
        pipe = pipe_dir(workdir, variant)
        vae = (_read_json(os.path.join(pipe, "stages", "vae.json")) or {}).get("results")
        entry = {"overrides": list(VARIANTS[variant]),
                 "vae": {k: vae.get(k) for k in ("steps", "first_loss", "final_loss")} if vae else None,
                 "world_model": world_model_loss(os.path.join(pipe, "world_model", "metrics.jsonl")),
                 "view": view_summary(os.path.join(workdir, f"view_{variant}")),
                 "exec": exec_summary(workdir, f"exec_{variant}", variant, rollout_batch)}
        out["variants"][variant] = _with_missing(entry)
        runs = checkpoint_runs(workdir, variant)
        if runs:
            out["variants"][variant]["checkpoints"] = {
                name: dict(step=step, sample_steps=sample_steps or None,
                           exec=exec_summary(workdir, name, variant, rollout_batch, step))
                for name, (step, sample_steps) in runs.items()}
    for kind, (sft_dir, _) in FINE_TUNES.items():
        runs = [v for v in VARIANTS if any(os.path.exists(os.path.join(workdir, f"{what}_{tuned_runs(v, kind)}"))
                                           for what in ("view", "exec"))]
        if not runs and not os.path.exists(os.path.join(workdir, sft_dir)):
            continue
        variant = runs[0] if runs else None
        sft = _read_json(os.path.join(workdir, sft_dir, "sft_results.json"))
        ens = sft["runs"][-1]["eval"].get("ens") if sft and sft.get("runs") else None
        out[kind] = dict(_with_missing({
            "sft": {"mean": ens["mean"], "ci95": ens["ci95"], "episodes": ens["episodes"]} if ens else None,
            "view": view_summary(os.path.join(workdir, f"view_{tuned_runs(variant, kind)}")) if variant else None,
            "exec": exec_summary(workdir, f"exec_{tuned_runs(variant, kind)}", variant, rollout_batch)
            if variant else None}), variant=variant)
    seen = {v: e["view"]["vae"]["mean"] for v, e in summary_rows(out).items() if "vae" in e.get("view", {})}
    out["best_vae_view"] = {"variant": max(seen, key=seen.get), "success": max(seen.values())} if seen else None
    return out


def checkpoint_runs(workdir: str, variant: str) -> dict[str, tuple[int, int]]:
    """The ``exec`` runs at a world-model checkpoint (:func:`checkpoint_run`) that ``workdir`` holds for ``variant``
    (a folder or a log): name -> (step, sampler steps or 0), by step."""
    prefix, out = f"exec_{variant}_at", {}
    for entry in sorted(os.listdir(workdir)) if os.path.isdir(workdir) else ():
        name = entry[:-len(".log")] if entry.endswith(".log") else entry
        step, _, sample_steps = name[len(prefix):].partition("_s")
        if name.startswith(prefix) and step.isdigit() and (not sample_steps or sample_steps.isdigit()):
            out[name] = (int(step), int(sample_steps or 0))
    return dict(sorted(out.items(), key=lambda kv: kv[1]))


def _with_missing(entry: dict) -> dict:
    """``entry`` with ``missing``: its parts that are absent (None) or were not summarised (a reason, in place)."""
    missing = {k: v if isinstance(v, str) else "not there" for k, v in entry.items()
               if v is None or isinstance(v, str)}
    return dict({k: v for k, v in entry.items() if k not in missing}, missing=missing)


def results_entries(summary: dict, workdir: str, *, data: str, command: str = "") -> dict[str, dict]:
    """``policy_sim_fidelity_small``: value the best success of the policy on frames round-tripped through a VAE
    (over the variants and the decoder-aware policy), beside every variant's figures."""
    best = summary.get("best_vae_view")
    if not best:
        raise SystemExit("bench_sim_fidelity: no view probe left a vae success to record")
    entry = common.record("", best["success"], None, best=best["variant"], variants=summary["variants"],
                          **{kind: summary.get(kind) for kind in FINE_TUNES},
                          device=common.workdir_device(workdir), data=data,
                          unit="MJX success of the policy on frames round-tripped through the VAE (sampled at T 0.5, "
                               "4 actions a decision, proprio missing; episodes: each probe's)",
                          **({"command": command} if command else {}))
    return {"policy_sim_fidelity_small": entry}


def summary_rows(summary: dict) -> dict[str, dict]:
    """Every variant's entry, then every fine-tune's under the name of its runs (``<variant>_<suffix>``; ``none_``
    where it left no probe or run)."""
    return dict(summary["variants"], **{tuned_runs(summary[k].get("variant") or "none", k): summary[k]
                                        for k in FINE_TUNES if k in summary})


def print_summary(summary: dict) -> None:
    rows = summary_rows(summary)
    if not rows:
        print("[sim-fidelity] no pipeline, probe or run of a variant here", flush=True)
    for name, r in rows.items():
        parts = []
        if r.get("vae"):
            parts.append(f"VAE loss {r['vae']['final_loss']:.4f}")
        if r.get("world_model"):
            parts.append(f"world model loss {r['world_model']['loss']:.4f}")
        if r.get("sft"):
            parts.append(f"SFT (ens) {common.interval_text(r['sft'])}")
        view = r.get("view") or {}
        if "real" in view and "vae" in view:
            d = view["difference"]
            parts.append(f"real {common.interval_text(view['real'])}, vae {common.interval_text(view['vae'])} "
                         f"({d['value']:+.3f} [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}])")
        if "round_trip_levels" in view:
            parts.append(f"round trip |error| {view['round_trip_levels']['mean_abs_error']['all']:.2f} levels")
        if r.get("exec"):
            parts.append("exec " + exec_text(r["exec"]))
        if r["missing"]:
            parts.append(f"missing: {', '.join(r['missing'])}")
        print(f"[sim-fidelity] {name}: " + "; ".join(parts), flush=True)
        for run, c in r.get("checkpoints", {}).items():
            sampler = f", {c['sample_steps']} sampler steps" if c["sample_steps"] else ""
            text = exec_text(c["exec"]) if isinstance(c["exec"], dict) else f"missing: {c['exec']}"
            print(f"[sim-fidelity] {run} (world model at step {c['step']}{sampler}): {text}", flush=True)


def exec_text(ex: dict) -> str:
    """An ``exec`` run's summary in a line: paid success, frame error and action gap at the first and last decision."""
    paid = ex["paid_success"]
    loss = f", world model loss {ex['world_model_loss']:.4f}" if "world_model_loss" in ex else ""
    return (f"paid {paid['rate']:.3f} [{paid['ci95'][0]:.3f}, {paid['ci95'][1]:.3f}], frame error "
            f"{ex['frame_error_first']:.3f} -> {ex['frame_error_last']:.3f}, action gap "
            f"{ex['action_gap_first']:.3f} -> {ex['action_gap_last']:.3f}" + (
                f" (the VAE alone at the first: {ex['frame_error_vae_first']:.3f}, "
                f"{ex['action_gap_vae_first']:.3f})" if "action_gap_vae_first" in ex else "") + loss)


def memory_fraction_option(text: str) -> dict[str, float]:
    """``--memory-fraction``'s ``kind=fraction,...`` as a dict, refused by name where a kind is not one of
    :data:`WEIGHTS`, is repeated, or its fraction is not a number in (0, 1]."""
    out = {}
    for part in (p for p in text.split(",") if p):
        kind, eq, value = part.partition("=")
        try:
            fraction = float(value)
        except ValueError:
            fraction = -1.0
        if not eq or kind not in WEIGHTS or kind in out or not 0 < fraction <= 1:
            raise SystemExit(f"bench_sim_fidelity: --memory-fraction takes kind=fraction with a kind of "
                             f"{', '.join(WEIGHTS)} (each once) and a fraction in (0, 1]; got {part!r}")
        out[kind] = fraction
    return out


def exec_checkpoints_option(text: str, world_model_steps: int) -> list[tuple[int, int]]:
    """``--exec-checkpoints``' ``STEP[:K],...`` as ``[(step, K or 0)]``, refused by name where a step is not in
    [1, --world-model-steps], K not in [1, 50] or an entry repeats, or where the checkpoints to keep would be more
    than 8."""
    out = []
    for part in (p for p in text.split(",") if p):
        step, colon, k = part.partition(":")
        ok = step.isdigit() and 1 <= int(step) <= world_model_steps and (not colon or (k.isdigit() and 1 <= int(k) <= 50))
        entry = (int(step), int(k or 0)) if ok else None
        if not ok or entry in out:
            raise SystemExit(f"bench_sim_fidelity: --exec-checkpoints takes STEP[:K],... with each STEP in [1, "
                             f"--world-model-steps={world_model_steps}] and K (flow sampler steps) in [1, 50], each "
                             f"once; got {part!r}")
        out.append(entry)
    every = checkpoint_period(out, world_model_steps)
    if out and world_model_steps // every > 8:
        raise SystemExit(f"bench_sim_fidelity: --exec-checkpoints {text}: the pipeline would keep a checkpoint every "
                         f"{every} steps, more than 8 of them; choose steps "
                         "with a larger common divisor with --world-model-steps")
    return out


def parse(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = cli.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=("run", "summary"))
    parser.add_argument("--workdir", required=True, help="the experiment's folder")
    parser.add_argument("--policy", default="", help="run: the supervised policy measured (.npz)")
    parser.add_argument("--config", default="sword:small")
    parser.add_argument("--gpus", default="0", help="run: comma list; variant i's jobs on the (i mod n)-th")
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"comma list of {', '.join(VARIANTS)}")
    parser.add_argument("--decoded-sft", action="store_true", help="run: also the decoder-aware policy")
    parser.add_argument("--decoded-variant", default="base",
                        help="run: the variant whose VAE the decoder-aware policy reads and whose world model it runs in")
    parser.add_argument("--imagined-sft", action="store_true",
                        help="run: also the policy fine-tuned on frames its demonstrations' actions make in the "
                             "--decoded-variant world model (rl.sft.decoded_source=world_model), measured there")
    parser.add_argument("--imagined-window", type=int, default=0,
                        help="run: the actions each replay of the imagined fine-tune runs from a real frame "
                             "(rl.sft.decoded_window; 0 = the exec arm's imagined rollout, 12 chunks x 4)")
    parser.add_argument("--sft-control", action="store_true",
                        help="run: also the same fine-tune on real frames only, measured in the same variant")
    parser.add_argument("--vae-steps", type=int, default=1000)
    parser.add_argument("--world-model-steps", type=int, default=12000)
    parser.add_argument("--policy-rollouts", type=int, default=20,
                        help="run: the policy's own episodes per task in the world model's and detector's data")
    parser.add_argument("--exec-steps", type=int, default=2, help="run: GRPO steps of each exec run")
    parser.add_argument("--exec-checkpoints", default="", metavar="STEP[:K],...",
                        help="run: also an exec run of --policy in each variant's world model at each of these "
                             "training steps (the pipeline keeps those checkpoints), sampled with K flow steps where "
                             "given (flow.sample_steps), one after another on a GPU no pipeline uses where there is one")
    parser.add_argument("--rollout-batch", type=int, default=64, help="start states per exec step (x 8)")
    parser.add_argument("--view-episodes-per-task", type=int, default=20, help="run: the view probe's, per view")
    parser.add_argument("--eval-episodes-per-task", type=int, default=10, help="run: the exec runs' evaluations")
    parser.add_argument("--sft-steps", type=int, default=1000)
    parser.add_argument("--sft-learning-rate", type=float, default=3e-4,
                        help="run: the fine-tune's peak rate (the policy was trained at 1e-3 falling to 1e-4)")
    parser.add_argument("--decoded-fraction", type=float, default=0.5)
    parser.add_argument("--deadline-s", type=float, default=0.0, help="run: stop what is still going after this")
    parser.add_argument("--leave-out", default="", metavar="JOB,...",
                        help="run: jobs of the plan not to run, e.g. exec_vae8x (none may be one another job waits for)")
    parser.add_argument("--memory-fraction", default="", metavar="KIND=F,...",
                        help=f"run: the GPU memory cap of every job of a kind ({', '.join(WEIGHTS)}) instead of its "
                             "share of the jobs that can overlap on its GPU, e.g. exec=0.3")
    common.add_summary_options(parser)
    args = parser.parse_args(argv)
    args.gpus = [g for g in args.gpus.split(",") if g]
    args.memory_fraction = memory_fraction_option(args.memory_fraction)
    args.leave_out = [j for j in args.leave_out.split(",") if j]
    args.exec_checkpoints = exec_checkpoints_option(args.exec_checkpoints, args.world_model_steps)
    args.variants = [v for v in args.variants.split(",") if v]
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown or not args.variants or len(set(args.variants)) < len(args.variants):
        raise SystemExit(f"bench_sim_fidelity: unknown or repeated variant(s) {unknown or args.variants}; "
                         f"--variants takes some of {', '.join(VARIANTS)}")
    if not args.gpus or len(set(args.gpus)) < len(args.gpus):
        raise SystemExit(f"bench_sim_fidelity: --gpus needs distinct GPUs, got {args.gpus}")
    counts = ("vae_steps", "world_model_steps", "exec_steps", "view_episodes_per_task", "eval_episodes_per_task",
              "sft_steps")
    if (any(getattr(args, k) < 1 for k in counts) or args.policy_rollouts < 0 or args.deadline_s < 0
            or args.imagined_window < 0):
        raise SystemExit(f"bench_sim_fidelity: --{', --'.join(k.replace('_', '-') for k in counts)} must be >= 1, "
                         "--policy-rollouts, --deadline-s and --imagined-window >= 0")
    if args.rollout_batch < 4 or args.rollout_batch % 4:
        raise SystemExit("bench_sim_fidelity: --rollout-batch must be a multiple of 4 (4 minibatches)")
    if not 0 < args.sft_learning_rate < 1:
        raise SystemExit(f"bench_sim_fidelity: --sft-learning-rate must be in (0, 1), got {args.sft_learning_rate}")
    if not 0 < args.decoded_fraction <= 1:
        raise SystemExit(f"bench_sim_fidelity: --decoded-fraction must be in (0, 1], got {args.decoded_fraction}")
    if (args.decoded_sft or args.imagined_sft or args.sft_control) and args.decoded_variant not in args.variants:
        raise SystemExit(f"bench_sim_fidelity: the fine-tuned policies run in the {args.decoded_variant!r} variant "
                         f"(--decoded-variant); add it to --variants (given: {','.join(args.variants)})")
    if args.mode == "run" and not os.path.isfile(args.policy):
        raise SystemExit(f"bench_sim_fidelity run needs --policy, the policy .npz (got {args.policy!r})")
    if args.mode == "run":
        plan(args)  # a --leave-out that cannot be honoured is refused before anything starts
    return args


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse(argv)
    if args.mode == "summary":
        summary = summarize(args.workdir, rollout_batch=args.rollout_batch)
        common.save_summary(summary, args.out, (lambda: results_entries(
            summary, args.workdir, data=common.summary_data(args.out, args.workdir), command=args.command)) if args.record else None)
        print_summary(summary)
        return summary
    summary = run(args)
    print_summary(summary)
    if summary["failed"] or summary["skipped"]:
        raise SystemExit(f"bench_sim_fidelity: failed {summary['failed']}, skipped {sorted(summary['skipped'])} "
                         f"(logs in {args.workdir})")
    return summary


if __name__ == "__main__":
    cli.run(main)
