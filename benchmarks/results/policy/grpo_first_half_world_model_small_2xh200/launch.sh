#!/bin/bash
# 2 x H200 of one host (32 CPU cores), 2026-11-30: GRPO in Sword's world model in the setting where ground-truth GRPO
# lifts the policy it trains (grpo_first_half_as_trained_small_2xh200, centred): keyframes of the first half of each
# demonstration, 12 decisions x 4 actions, 64 starts x 8, one sampling round, T 0.5, proprio missing, centred
# advantages, lr 1e-4, seeds 0-2, 20 steps, 500 MJX evaluation episodes from rest at steps 0 and 20 (greedy ensembled,
# sampled re-planning every action, proprio masked, and sampled as trained: 4 actions of each sampled chunk, proprio
# missing). Two arms: exec (the world model's frames, each rollout paid by the real outcome of its actions, executed
# on MJX) and cal (the same for its first 4 steps, then the detector's reward at the threshold those steps set, which
# keeps its false successes on the policy's own closed loop at 5% or less). The world model, VAE and detector are the
# 30,000-step ones built beside the ground-truth runs (their record's pack.log: the bundle of 14 parts); the command
# built only the data stage (the same demonstrations). 3 runs per GPU.
R=/tmp/runs
JAX_PLATFORMS=cpu python3 -m train.bundle unpack /tmp/wm $R/bp > $R/unpack.log 2>&1 || exit 1
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/W --policy $P --bundle /tmp/wm --gpus 0,1 \
  --seeds 0,1,2 --arms exec,cal --calibrate-steps 4 --keyframe-fraction 0.5 --horizon 12 --actions-per-decision 4 \
  --scale-by-std false --rollout-batch 64 --steps 20 --eval-every 20 --eval-episodes-per-task 50 --vae-variant vae8x \
  --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false \
  --deadline-s 1330 --grace-s 170 > $R/W.out 2>&1   # the record's main.log
# the record: the work dir W (pipeline/: the data stage's config and log only); the summary and the figures
REC=benchmarks/results/policy/grpo_first_half_world_model_small_2xh200
python -m benchmarks.bench_grpo_reward_source summary --workdir $REC --out $REC/grpo_reward_source
python -m benchmarks.bench_grpo_reward_source figure --workdir $REC --out $REC.png
python -m benchmarks.bench_grpo_reward_source figure --episodes --evaluated sampled_as_trained \
  --workdirs benchmarks/results/policy/grpo_first_half_as_trained_small_2xh200/centred,$REC --out ${REC}_episodes.png \
  --title "small; first-half keyframes, 12 x 4 actions, 64 x 8; seeds 0-2; 2 x H200"
