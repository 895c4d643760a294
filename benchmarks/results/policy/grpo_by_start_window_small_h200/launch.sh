#!/bin/bash
# 1 x H200 (16 CPU cores), 2026-12-01: GRPO in Sword's world model paid by executing its rollouts' actions on MJX
# (exec) from keyframes after the grasp only: the second half of each demonstration (--keyframe-from 0.5
# --keyframe-fraction 1.0), otherwise as grpo_by_start_small_h200 (12 x 4, 64 x 8, T 0.5, proprio missing, centred,
# lr 1e-4, seeds 0-1). Planned for 4 steps; the run's time limit (--deadline-s 520, 45 s grace) stopped both runs
# after step 1, so the record reads step 1's 512 rollouts per seed (before any update: the supervised policy's).
# The world model, VAE and detector are the 30,000-step bundle of the first-half record; the command built only the
# data stage. 2 runs on the one GPU.
R=/tmp/runs
JAX_PLATFORMS=cpu python3 -m train.bundle unpack /tmp/wm $R/bp > $R/unpack.log 2>&1 || exit 1
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/W --policy $P --bundle /tmp/wm --gpus 0 \
  --seeds 0,1 --arms exec --keyframe-from 0.5 --keyframe-fraction 1.0 --horizon 12 --actions-per-decision 4 \
  --scale-by-std false --rollout-batch 64 --steps 4 --eval-every 100 --eval-episodes-per-task 1 --vae-variant vae8x \
  --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false \
  --deadline-s 520 --grace-s 45 > $R/W.out 2>&1   # the record's main.log
REC=benchmarks/results/policy/grpo_by_start_window_small_h200
python -m benchmarks.bench_grpo_reward_source summary --workdir $REC --out $REC/grpo_reward_source
