#!/bin/bash
# 2-core CPU (the MuJoCo C engine), 2026-11-29: is GRPO's short-rollout gradient signal, and does it point where the
# from-rest gradient does? policy_d50, seed 0, T 0.5, proprio masked, 4 actions a decision, GRPO's default objective
# (loss_norm trajectory, advantages scaled by the std), at the starting policy, no training. 64 keyframe groups (every
# phase of 50 expert demonstrations) x 8 and 40 groups at rest x 8, every trajectory to the episode limit (220 actions).
python -m train.gen_data --task all --episodes 5 --out /tmp/hz/demos.hdf5 --stop-at-success --resolution 128 --init-split train
python -m benchmarks.bench_grpo_gradient_signal --policy runs/p/policy_d50.npz --demos /tmp/hz/demos.hdf5 \
  --out benchmarks/results/policy/grpo_gradient_signal_small_cpu --groups 64 --rest-groups 40 --settings short,short_eventual
