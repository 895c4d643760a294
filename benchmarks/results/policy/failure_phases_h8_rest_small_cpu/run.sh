#!/bin/bash
# 2-core CPU (the MuJoCo C engine), 2026-11-29: as ../failure_phases_h12_rest_small_cpu (the same 300 episodes from
# rest and 256 of their start states: same seed), the rollouts 8 decisions long instead of 12. Not recorded to
# latest.json.
python -m benchmarks.bench_failure_phases --policy runs/p/policy_d50.npz --out benchmarks/results/policy/failure_phases_h8_rest_small_cpu \
  --episodes 300 --starts 256 --horizon 8 --workers 2 --branch-from rest
