#!/bin/bash
# one H200 with 16 CPU cores, 2026-11-29: branched short ground-truth GRPO with open starts and centred advantages.
# Four runs side by side on the GPU (success alone at seeds 0-2, closed by the value at seed 0), 1,200 s deadline:
# it stopped them during the step-40 evaluation, so their last point is step 30. A resume to finish that evaluation
# failed at its checkpoint restore (the traceback ends each log); checkpoint.abstract_like now restores NumPy leaves.
C="--workdir runs/gv2 --policy runs/p/policy_d50.npz --gpus 0 --steps 40 --eval-every 10 --rollout-batch 64 --horizon 4
   --value-episodes 512 --value-steps 2000 --scale-by-std false --branch-starts open --deadline-s 1200"
python3 -m benchmarks.bench_grpo_value run $C --arms success --seeds 0,1,2 &
python3 -m benchmarks.bench_grpo_value run $C --arms value --seeds 0 &
wait
python3 -m benchmarks.bench_grpo_value summary --workdir runs/gv2 --out runs/gv2/grpo_value --record --record-as open
# the noise-only control, a second run on one H200 (launch: ../grpo_branched_open_b256_small_h200/launch.sh):
#   --arms shuffled --seeds 0,1,2 --steps 30 --deadline-s 1150; its records under shuffled/, the summary over both
