#!/bin/bash
# one H200 with 16 CPU cores, 2026-11-29: success alone at 256 open starts x 8, seeds 0-2, centred advantages,
# beside the KL-anchored run at 64 starts (../grpo_branched_open_kl_small_h200). 1,180 s deadline with 240 s grace:
# at the deadline every run was asked to stop, evaluated its step in flight (47, 40 and 39) and checkpointed it.
C="--policy runs/p/policy_d50.npz --gpus 0 --arms success --horizon 4 --value-episodes 512 --value-steps 2000
   --scale-by-std false --branch-starts open --steps 50 --eval-every 25 --deadline-s 1180 --grace-s 240"
python3 -m benchmarks.bench_grpo_value run --workdir runs/gv5 $C --seeds 0,1,2 --rollout-batch 256 &
python3 -m benchmarks.bench_grpo_value run --workdir runs/gv6 $C --seeds 0 --rollout-batch 64 --kl-coef 0.04 &
wait
python3 -m benchmarks.bench_grpo_value summary --workdir runs/gv5 --out runs/gv5/grpo_value --record --record-as open_b256
python3 -m benchmarks.bench_grpo_value summary --workdir runs/gv6 --out runs/gv6/grpo_value --record --record-as open_kl
