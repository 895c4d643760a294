# 4 x H200 of one host, 2026-11-27: Sword's small pipeline (seed 0, policy_d50, 20 of its episodes per task in the
# world model's and detector's data), then refreshed runs of 0 GRPO steps: step 0's evaluation (500 MJX episodes)
# and refresh (64 real episodes as 8 starts x 8), at action guidance 1 (GPU 0), 2 and 3 (GPUs 1, 2), and a second
# pipeline trained with action dropout 0.1 sampled at guidance 2 (GPU 3)
python -m benchmarks.bench_grpo_refresh run --workdir runs/p42 --policy runs/p/policy_d50.npz \
  --gpus 0 --seeds 0 --arms refreshed --policy-rollouts 20 --data-backend cpu \
  --rl.refresh.calibration=separation --rl.imagined.eval_replay_episodes=0 --refresh-every 10 --steps 0 \
  --budget 64 --rl.refresh.group_size=8 --deadline-s 1150 \
  --run-variant "g2=--flow.guidance_scale=2" --run-variant "g3=--flow.guidance_scale=3" --run-variant-gpus 1,2 \
  --variant "ad=--flow.action_dropout=0.1 --flow.guidance_scale=2" --variant-gpus 3
