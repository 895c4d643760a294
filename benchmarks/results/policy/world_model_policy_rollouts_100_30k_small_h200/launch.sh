# one H200 (16 CPU cores), 2026-11-30. The policy is the one committed with grpo_rest_h12_seeds_small_2xh200.
# The recipe of world_model_policy_split_30k_small_h200 (small, 8x VAE of 1,000 steps, 30,000 world-model steps of
# 32 segments, EMA 0.999, unrolled layers, seed 0) with 100 rollouts of the supervised policy per task in the world
# model's data instead of 20 (1,000 instead of 200, each with 2 styled copies beside the 200 expert episodes'),
# recorded by 4 worker processes; the VAE trained beside them. Up to the world model; the trainer measured the four
# splits (held-out expert, held-out policy, training policy, training) every 1,000 steps.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python -m train.pipeline --config sword:small --seed 0 --workdir runs/p100 --stop-after world_model \
  --skip probe,evaluate --parallel 2 --data.policy_rollouts_per_task=100 --rl.sft.episodes_per_task=20 \
  --rl.sft.init=$P --vae.train_steps=1000 --trainer.steps=30000 --sim.backend=cpu --vae.dim_mult=1,4,4 \
  --vae.temporal_downsample=true,true --trainer.ema_decay=0.999 --model.scan_layers=false \
  --data.policy_rollout_workers=4 > runs/p100.out 2>&1
