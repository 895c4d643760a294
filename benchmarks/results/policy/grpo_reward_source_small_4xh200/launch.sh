# 4 x H200 of one host, 2026-11-28: the reward-source experiment, one command, a 1,250 s deadline (every run
# finished before it: 1,241 s in all). policy_d50 as in ../grpo_reward_source_small_4xh100/ (re-made by the same
# SFT command; greedy with ensembling 0.704 [0.663, 0.742] on 500 episodes).
python3 -m benchmarks.bench_grpo_reward_source run --workdir /tmp/runs/rs --policy /tmp/runs/p/policy_d50.npz \
  --gpus 0,1,2,3 --seeds 0,1,2 --steps 20 --eval-every 10 --rollout-batch 64 --deadline-s 1250
# here, on the copied records (json, jsonl, logs; no checkpoints):
python -m benchmarks.bench_grpo_reward_source summary --workdir benchmarks/results/policy/grpo_reward_source_small_4xh200 \
  --out benchmarks/results/policy/grpo_reward_source_small_4xh200/grpo_reward_source --record
