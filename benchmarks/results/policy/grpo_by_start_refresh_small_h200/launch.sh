#!/bin/bash
# 1 x H200 (16 CPU cores), 2026-12-01: does a refresh on the policy's own real episodes make the world model keep
# more of reality's payment where it loses it (starts in the first 24 actions)? Ground-truth GRPO on MJX (gt) beside
# GRPO in Sword's world model refreshed once, at step 0, and paid by executing its rollouts' actions on MJX (rexec):
# 128 MJX episodes of the policy from rest (its real-episode budget), the world model fine-tuned on them mixed with
# its training latents for 1,000 steps at 3e-5 (rl.refresh defaults otherwise), the detector fine-tuned on their
# replays and its threshold set on held-out replays (false success <= 5%). Otherwise as grpo_by_start_small_h200,
# whose exec runs are the world model as trained: keyframes of every phase (--keyframe-fraction 1.0), 12 x 4,
# 64 x 8, one sampling round, T 0.5, proprio missing, centred, lr 1e-4, seeds 0-1, 4 steps. The evaluations
# (10 episodes at steps 0 and 4) only bracket the steps. The world model, VAE and detector are the 30,000-step
# bundle; the command built the data stage and encoded its training episodes with the bundle's VAE (latents.log).
# 4 runs on the one GPU.
R=/tmp/runs
JAX_PLATFORMS=cpu python3 -m train.bundle unpack /tmp/wm $R/bp > $R/unpack.log 2>&1 || exit 1
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/X --policy $P --bundle /tmp/wm --gpus 0 \
  --seeds 0,1 --arms gt,rexec --keyframe-fraction 1.0 --horizon 12 --actions-per-decision 4 \
  --scale-by-std false --rollout-batch 64 --steps 4 --eval-every 100 --eval-episodes-per-task 1 --vae-variant vae8x \
  --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false \
  --refresh-every 100 --refresh-episodes 128 --refresh-budget 128 --refresh-set rl.refresh.world_model_steps=1000 \
  --deadline-s 1330 --grace-s 90 > $R/X.out 2>&1   # the record's main.log
# the record: the work dir X (pipeline/: the data stage's config and log only; each refresh's record.json, not its
# weights) and its summary
REC=benchmarks/results/policy/grpo_by_start_refresh_small_h200
python -m benchmarks.bench_grpo_reward_source summary --workdir $REC --out $REC/grpo_reward_source
python -m benchmarks.bench_grpo_reward_source figure --by-start --workdirs $REC --out $REC.png \
  --title "small, 30k world model + 128-episode refresh; 12 x 4, 64 x 8; seeds 0-1; 1 x H200"
