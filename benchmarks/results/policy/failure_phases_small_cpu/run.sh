#!/bin/bash
# 2-core CPU (the MuJoCo C engine), 2026-11-29: where policy_d50 fails from rest and where GRPO's short rollouts
# (4 decisions of 4 actions, groups of 8) have mixed outcomes. T 0.5, proprio masked, seed 0.
python -m benchmarks.bench_failure_phases --policy runs/p/policy_d50.npz --out benchmarks/results/policy/failure_phases_small_cpu \
  --episodes 300 --starts 256 --workers 2 --record
