#!/bin/bash
# 2 x H200 of one host (16 CPU cores each), 2026-11-29. policy_d50 re-made first on GPU 0 by the SFT command below
# (its weights, log and results in policy_d50/; greedy with ensembling 0.790 [0.728, 0.841] on the C engine's first 20
# evaluation states per task, 200 episodes). Then two experiments side by side, success alone, centred advantages,
# XLA's deterministic GPU ops, seeds 0-2 each: from rest cut at 12 decisions (48 actions), 256 starts x 8, on GPU 0
# (this folder, rest_h12), and from rest to the episode limit, 64 starts x 8, on GPU 1
# (../grpo_rest_whole_seeds_small_2xh200, rest_whole). A 1,000 s deadline with 240 s grace: the 12-decision runs
# stopped at steps 15, 17 and 14 and were evaluated there; the whole-episode runs reached steps 10-11, and two of
# them were stopped after the grace while training step 11, so their last evaluation is step 10's.
R=runs
python -m benchmarks.bench_policy sft --config sword:small --out $R/p --demos-per-task 50 --execute ens \
    --eval-episodes 20 --workers 14
C="--policy $R/p/policy_d50.npz --arms success --branch-starts rest --value-episodes 0 --scale-by-std false \
   --steps 30 --eval-every 10 --deadline-s 1000 --grace-s 240 --deterministic --seeds 0,1,2"
python -m benchmarks.bench_grpo_value run --workdir $R/gv9 $C --gpus 0 --horizon 12 --rollout-batch 256 &
python -m benchmarks.bench_grpo_value run --workdir $R/gv10 $C --gpus 1 --horizon 55 --rollout-batch 64 &
wait
python -m benchmarks.bench_grpo_value summary --workdir $R/gv9 --out $R/gv9/grpo_value --record --record-as rest_h12
python -m benchmarks.bench_grpo_value summary --workdir $R/gv10 --out $R/gv10/grpo_value --record --record-as rest_whole
