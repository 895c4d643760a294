#!/bin/bash
# 2-core CPU (the MuJoCo C engine), 2026-12-01: the policy committed with grpo_rest_h12_seeds_small_2xh200, 300
# episodes from rest as GRPO's rollouts run it (T 0.5, proprio masked, 4 actions a decision); from 512 of their
# decisions within the first 12 (48 actions), the next 12 decisions' recorded actions replayed open loop from the
# recorded state and from it with the bowl (where not held) or the plate moved by 0.25, 0.5, 1 and 2 pixels of the
# 128-pixel agent view, and by 1e-6 m, 8 random directions each (a start is over the plate with the bowl within 5 cm
# of it in xy, the default --over-m). Not recorded to latest.json.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python -m benchmarks.bench_outcome_determinacy --policy $P --out benchmarks/results/policy/outcome_determinacy_small_cpu \
  --episodes 300 --starts 512 --starts-before 12 --draws 8 --workers 2
