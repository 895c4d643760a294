#!/bin/bash
# 2-core CPU (the MuJoCo C engine), 2026-11-29: as ../failure_phases_small_cpu (the same 300 episodes and 256 branch
# points: same seed), the short rollouts 12 decisions long instead of 4. Not recorded to latest.json. Run again the same
# day with the per-task breakdown (per_task in failure_phases.json): every other count came out identical.
python -m benchmarks.bench_failure_phases --policy runs/p/policy_d50.npz --out benchmarks/results/policy/failure_phases_h12_small_cpu \
  --episodes 300 --starts 256 --horizon 12 --workers 2
