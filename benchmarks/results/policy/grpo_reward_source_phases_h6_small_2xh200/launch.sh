#!/bin/bash
# 2 x H200 of one host (32 CPU cores), 2026-11-30: GRPO at 6 decisions of 8 actions from keyframes of every phase,
# ground truth on MJX (gt) beside the world model's frames paid by the real outcome of their actions (exec), seeds 0-2,
# 64 starts x 8, 20 steps, 500 MJX evaluation episodes at steps 0 and 20 (or at the step a run was asked to stop).
# The world model, VAE and detector were read from the bundle of world_model_policy_split_30k_small_h200; the
# demonstrations were built by the data stage in grpo_horizon_honesty_small_2xh200/launch.sh (the same command).
R=/tmp/runs; W=$R/rs12; mkdir -p $W
python3 -m train.bundle unpack /tmp/wm /tmp/bp > $W/unpack.log 2>&1 || { echo "summary rc unpack-failed" >> $R/rs12.out; exit 1; }
python3 -m benchmarks.bench_grpo_reward_source run --workdir $W --policy $R/p/policy_d50.npz \
  --bundle /tmp/wm --pipeline $R/hz/data/pipeline --vae-variant vae8x --world-model-set trainer.ema_decay=0.999 \
  --world-model-set model.scan_layers=false --gpus 0,1 --seeds 0,1,2 --arms gt,exec --horizon 6 \
  --keyframe-fraction 1.0 --actions-per-decision 8 --scale-by-std false --rollout-batch 64 --steps 20 --eval-every 20 \
  --eval-episodes-per-task 50 --deadline-s ${DEADLINE:-640} --grace-s ${GRACE:-200} > $R/rs12.out 2>&1
echo "rs rc $?" >> $R/rs12.out
python3 -m benchmarks.bench_grpo_reward_source summary --workdir $W --out $R/rs12_summary > $R/summary12.log 2>&1
echo "summary rc $?" >> $R/rs12.out
