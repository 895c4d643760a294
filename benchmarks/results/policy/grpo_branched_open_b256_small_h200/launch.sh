#!/bin/bash
# one H200 with 16 CPU cores, 2026-11-29: the noise-only control (shuffled returns) at seeds 0-2, 64 open starts x 8,
# beside success alone at 256 open starts x 8, seed 0; centred advantages; 1,150 s deadline. The four runs reached
# step 30; the launchers were stopped before their deadline so that the step-30 evaluations could finish.
# The control's records are in ../grpo_branched_open_small_h200/shuffled (beside the success arm at 64 starts).
C="--policy runs/p/policy_d50.npz --gpus 0 --steps 30 --eval-every 10 --horizon 4 --value-episodes 512 --value-steps 2000
   --scale-by-std false --branch-starts open --deadline-s 1150"
python3 -m benchmarks.bench_grpo_value run --workdir runs/gv3 $C --rollout-batch 64 --arms shuffled --seeds 0,1,2 &
python3 -m benchmarks.bench_grpo_value run --workdir runs/gv4 $C --rollout-batch 256 --arms success --seeds 0 &
wait
python3 -m benchmarks.bench_grpo_value summary --workdir runs/gv4 --out runs/gv4/grpo_value --record --record-as open_b256
