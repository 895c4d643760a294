#!/bin/bash
# 2 x H200 of one host (32 CPU cores), 2026-11-30: ground-truth GRPO on MJX (the reward-source experiment's gt arm)
# from keyframes of the first half of each demonstration, 12 decisions x 4 actions, 64 starts x 8, one sampling
# round, T 0.5, proprio missing, lr 1e-4, seeds 0-2, 500 MJX evaluation episodes from rest at steps 0, 20 and 40:
# greedy (ensembled), sampled re-planning every action (true proprio, and proprio masked), and sampled as trained
# (4 actions of each sampled chunk executed, proprio missing: sampled_as_trained). Two advantage rules: scaled by
# the group's std (std) and only centred (centred). std's command built Sword's small pipeline on GPU 0 (data, then
# the 30,000-step world model, VAE and detector, packed by train.bundle: pack.log; the bundle is not tracked); all
# six runs shared GPU 1 and read std's demonstrations. Each ran 20 steps, then was resumed to 40 (runs resume
# exactly; rl.grpo.steps is not part of a run's identity), 3 runs per GPU.
R=/tmp/runs
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
C="--policy $P --seeds 0,1,2 --arms gt --keyframe-fraction 0.5 --rollout-batch 64 --horizon 12
   --actions-per-decision 4 --eval-every 20 --eval-episodes-per-task 50 --vae-variant vae8x
   --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false"
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/S $C --steps 20 --gpus 0,1 --pipeline-gpus 0 \
  --scale-by-std true --world-model-steps 30000 --policy-rollouts 20 --deadline-s 1650 --grace-s 60 > $R/S.out 2>&1 &
sleep 20
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/K $C --steps 20 --gpus 1 --pipeline $R/S/pipeline \
  --scale-by-std false --deadline-s 1500 --grace-s 60 > $R/K.out 2>&1 &
wait
JAX_PLATFORMS=cpu python3 -m train.bundle pack $R/S/pipeline $R/bundle --part-mib 15.9 > $R/pack.log 2>&1
# resumed to step 40, 3 runs on each GPU
C="$C --pipeline $R/S/pipeline --steps 40 --deadline-s 420 --grace-s 20"
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/S $C --gpus 0 --scale-by-std true > $R/S40.out 2>&1 &
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/K $C --gpus 1 --scale-by-std false > $R/K40.out 2>&1 &
wait
# the record: S -> std, K -> centred (std.out, centred.out: both commands' output); the summaries:
REC=benchmarks/results/policy/grpo_first_half_as_trained_small_2xh200
for w in std centred; do
  python -m benchmarks.bench_grpo_reward_source summary --workdir $REC/$w --out $REC/$w/grpo_reward_source
done
