#!/bin/bash
# 1 x H200 (16 CPU cores), 2026-12-01: does a fine-tune on the world model's own closed loop make it keep more of
# reality's payment where it loses it (starts in the first 24 actions)? Ground-truth GRPO on MJX (gt) beside GRPO in
# Sword's world model refreshed once, at step 0, and paid by executing its rollouts' actions on MJX (rexec). The
# refresh: 128 MJX episodes of the policy from rest, and the policy's closed loop in the world model from 64 keyframe
# starts x 8 (drawn as GRPO's keyframes are, for steps a run never reaches; 12 x 4 actions, none stopped at a
# success), each trajectory's actions executed on MJX from its keyframe's recorded state (640 real episodes in all).
# The world model was fine-tuned for 2,000 steps at 1e-4 on its training latents mixed with the 128 episodes, half of
# every batch's rows being closed-loop segments (the world model's own context, the real latents of the executed
# actions), every 8th trajectory's segments held out to measure the fine-tune before and after it. Otherwise as
# grpo_by_start_refresh_small_h200: keyframes of every phase, 12 x 4, 64 x 8, one sampling round, T 0.5, proprio
# missing, centred, lr 1e-4, seeds 0-1, 4 steps, the 30,000-step bundle. In this run the executed frames were encoded
# after the keyframe held still for four frames, not after its real history (see RESULTS).
# The control (control/: rexec refreshed alike on the 128 episodes only, seed 0, started beside it on the same GPU
# with --pipeline and --latents of this run) ran its refresh and then ran out of GPU memory at its first GRPO step.
R=/tmp/runs
JAX_PLATFORMS=cpu python3 -m train.bundle unpack /tmp/wm $R/bp > $R/unpack.log 2>&1 || exit 1
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
COMMON="--policy $P --bundle /tmp/wm --gpus 0 --keyframe-fraction 1.0 --horizon 12 --actions-per-decision 4 \
  --scale-by-std false --rollout-batch 64 --steps 4 --eval-every 100 --eval-episodes-per-task 1 --vae-variant vae8x \
  --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false --refresh-every 100 \
  --refresh-episodes 128 --refresh-set rl.refresh.world_model_steps=2000 \
  --refresh-set rl.refresh.world_model_learning_rate=0.0001 --grace-s 90"
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/X $COMMON --seeds 0,1 --arms gt,rexec \
  --refresh-budget 640 --refresh-set rl.refresh.closed_loop_starts=64 --refresh-set rl.refresh.closed_loop_share=0.5 \
  --deadline-s 1300 > $R/X.out 2>&1 &   # the record's main.log
until grep -q "rexec_s0 on GPU" $R/X.out; do sleep 5; done; sleep 20
XLA_PYTHON_CLIENT_MEM_FRACTION=0.25 python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/Y $COMMON \
  --pipeline $R/X/pipeline --latents $R/X/latents.npz --seeds 0 --arms rexec --refresh-budget 128 \
  --deadline-s 1050 > $R/Y.out 2>&1   # control/main.log
wait
# the record: the work dir X (pipeline/: the data stage's config and log only; each refresh's record.json, not its
# weights), Y as control/, and the summary
REC=benchmarks/results/policy/grpo_by_start_closed_loop_small_h200
python -m benchmarks.bench_grpo_reward_source summary --workdir $REC --out $REC/grpo_reward_source
python -m benchmarks.bench_grpo_reward_source figure --by-start --workdirs $REC --out $REC.png \
  --title "small, 30k world model + closed-loop refresh; 12 x 4, 64 x 8; seeds 0-1; 1 x H200"
