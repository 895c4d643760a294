#!/bin/bash
# 2-core CPU (the MuJoCo C engine), 2026-11-29: ../failure_phases_h12_rest_small_cpu (same seed, policy, 300 start
# states at rest and 256 branch starts) with a whole chunk of 8 actions a decision instead of 4: the episodes from
# rest, and rollouts of 6 decisions (48 actions, the rest recipe's cut) from their first states. Not recorded to
# latest.json.
python -m benchmarks.bench_failure_phases --policy benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz --out benchmarks/results/policy/failure_phases_h6x8_rest_small_cpu \
  --episodes 300 --starts 256 --horizon 6 --actions-per-decision 8 --workers 2 --branch-from rest
