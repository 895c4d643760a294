#!/bin/bash
# 1 x H200 (16 CPU cores), 2026-12-01: where the world model's closed loop keeps reality's payment, by the start's
# step in its demonstration. Ground-truth GRPO on MJX (gt) beside GRPO in Sword's world model paid by executing its
# rollouts' actions on MJX (exec), in the setting of grpo_first_half_world_model_small_2xh200 but from keyframes of
# every phase (--keyframe-fraction 1.0): 12 decisions x 4 actions, 64 starts x 8, one sampling round, T 0.5, proprio
# missing, centred advantages, lr 1e-4, seeds 0-1, 4 steps. Every step counts its trajectories, their real successes
# and (exec) the detector's verdicts by the keyframe's step (sword_jax.rl.imagined_check.outcomes_by_start); the
# summary pools them per run (by_start). The evaluations (10 episodes at steps 0 and 4) only bracket the steps.
# The world model, VAE and detector are the 30,000-step bundle of the first-half record; the command built only the
# data stage. 4 runs on the one GPU.
R=/tmp/runs
JAX_PLATFORMS=cpu python3 -m train.bundle unpack /tmp/wm $R/bp > $R/unpack.log 2>&1 || exit 1
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/N --policy $P --bundle /tmp/wm --gpus 0 \
  --seeds 0,1 --arms gt,exec --keyframe-fraction 1.0 --horizon 12 --actions-per-decision 4 \
  --scale-by-std false --rollout-batch 64 --steps 4 --eval-every 100 --eval-episodes-per-task 1 --vae-variant vae8x \
  --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false \
  --deadline-s 700 --grace-s 60 > $R/N.out 2>&1   # the record's main.log
# the record: the work dir N (pipeline/: the data stage's config and log only) and its summary
REC=benchmarks/results/policy/grpo_by_start_small_h200
python -m benchmarks.bench_grpo_reward_source summary --workdir $REC --out $REC/grpo_reward_source
python -m benchmarks.bench_grpo_reward_source figure --by-start --workdirs $REC --out $REC.png \
  --title "small, 30k world model; 12 x 4, 64 x 8; steps 1-4; seeds 0-1; 1 x H200"
