#!/bin/bash
# one H200 with 16 CPU cores, the four runs side by side on it, 1,250 s deadline
python3 -m benchmarks.bench_grpo_value run --workdir runs/gv --policy runs/p/policy_d50.npz --gpus 0 \
  --seeds 0,1 --steps 80 --eval-every 10 --rollout-batch 64 --horizon 4 --value-episodes 512 --value-steps 2000 \
  --deadline-s 1250
python3 -m benchmarks.bench_grpo_value summary --workdir runs/gv --out runs/gv/grpo_value --record
