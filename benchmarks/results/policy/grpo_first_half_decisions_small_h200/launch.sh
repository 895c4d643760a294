#!/bin/bash
# one H200 (16 CPU cores), 2026-11-30: ground-truth GRPO on MJX (the reward-source experiment's gt arm) from keyframes
# of the first half of each demonstration (--keyframe-fraction 0.5) at three decision lengths: 6 x 8 actions (h6x8),
# 4 x 8 (h4x8) and 12 x 4 (h12x4); 64 starts x 8, one sampling round, T 0.5, proprio missing, centred advantages,
# lr 1e-4, seeds 0-2, 20 steps, 500 MJX evaluation episodes from rest at steps 0 and 20. All three read the
# demonstrations of h6x8's data stage (sword:small, the policy's 20 rollouts per task). h6x8's command also began
# the world model's pipeline after its data stage; that was stopped before its VAE had finished (its logs are left
# out) and nothing here reads it. h4x8 started beside h6x8 once the pipeline was stopped; h12x4 after both.
R=/tmp/runs
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
C="--policy $P --gpus 0 --seeds 0,1,2 --arms gt --keyframe-fraction 0.5 --scale-by-std false --rollout-batch 64
   --steps 20 --eval-every 20 --eval-episodes-per-task 50 --vae-variant vae8x
   --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false"
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/A $C --horizon 6 --actions-per-decision 8 \
  --world-model-steps 30000 --policy-rollouts 20 --deadline-s 1600 --grace-s 120 > $R/A.out 2>&1
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/B $C --pipeline $R/A/pipeline --horizon 4 \
  --actions-per-decision 8 --deadline-s 1000 --grace-s 120 > $R/B.out 2>&1
python3 -m benchmarks.bench_grpo_reward_source run --workdir $R/C $C --pipeline $R/A/pipeline --horizon 12 \
  --actions-per-decision 4 --deadline-s 470 --grace-s 110 > $R/C.out 2>&1
# the summaries in the record (A -> h6x8, B -> h4x8, C -> h12x4):
REC=benchmarks/results/policy/grpo_first_half_decisions_small_h200
for h in h6x8 h4x8 h12x4; do
  python -m benchmarks.bench_grpo_reward_source summary --workdir $REC/$h --out $REC/$h/grpo_reward_source
done
