#!/bin/bash
# 2-core CPU (the MuJoCo C engine), 2026-11-29: the same 300 episodes from rest as ../failure_phases_h12_small_cpu
# (same seed), the 12-decision rollouts branched from 256 of the episodes' start states (at rest) instead of from
# running decisions: what GRPO from rest cut at 12 decisions (rl.env.starts=rest) would be paid. Not recorded to
# latest.json.
python -m benchmarks.bench_failure_phases --policy runs/p/policy_d50.npz --out benchmarks/results/policy/failure_phases_h12_rest_small_cpu \
  --episodes 300 --starts 256 --horizon 12 --workers 2 --branch-from rest
