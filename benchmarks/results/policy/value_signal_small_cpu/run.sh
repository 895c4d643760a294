#!/bin/bash
# 2-core CPU (the MuJoCo C engine), 2026-11-29: does a fitted value rank a GRPO group's trajectories by their later
# real outcome? policy_d50, seed 0, T 0.5, proprio masked, 4 actions a decision. The value is fitted six times (300
# and 1,000 steps x fit seeds 0-2) to the same 256 episodes from rest (205 fitted, 51 held out); the groups are 32
# keyframes of every phase of 50 expert demonstrations (5 per task) x 8 trajectories, each run to the episode limit.
python -m train.gen_data --task all --episodes 5 --out /tmp/hz/demos.hdf5 --stop-at-success --resolution 128 --init-split train
python -m benchmarks.bench_value_signal --policy runs/p/policy_d50.npz --demos /tmp/hz/demos.hdf5 \
  --out benchmarks/results/policy/value_signal_small_cpu --value-episodes 256 --value-steps 300,1000 --fit-seeds 0,1,2 \
  --groups 32 --group-size 8
