#!/bin/bash
# 2 x H200 of one host (32 CPU cores), 2026-12-01, 1,480 s deadline: does a larger world model predict the supervised
# policy's unseen rollouts better? small's pipeline (seed 0, the 8x VAE, 20 rollouts of the policy per task beside
# the 200 expert episodes, EMA 0.999, unrolled layers) with the world model widened and deepened, 10,000 steps, one
# size per GPU: dim 1,024 x 16 layers (big/, 280.1 M parameters) and dim 768 x 12 layers (mid/, 120.0 M), heads of
# 64, ffn 4 x dim. Its trainer measured the same fixed segments as world_model_policy_split_30k_small_h200 (small
# itself, 36.7 M) every 1,000 steps. Then GRPO in each world model paid by executing its rollouts' actions on MJX
# (exec, 12 x 4 from keyframes of every phase, 64 x 8, T 0.5, proprio missing, centred, 4 steps) until the deadline:
# mid/ ran its 4 steps, big/ was stopped during its step-0 evaluation.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
C="--policy $P --seeds 0 --arms exec --horizon 12 --keyframe-fraction 1.0 --actions-per-decision 4 --vae-variant vae8x
   --world-model-steps 10000 --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false
   --world-model-set data.policy_rollout_workers=4 --rollout-batch 64 --scale-by-std false --steps 4 --eval-every 100
   --eval-episodes-per-task 1 --grace-s 45 --deadline-s 1480"
python3 -m benchmarks.bench_grpo_reward_source run --workdir runs/big --gpus 0 $C \
  --world-model-set model.dim=1024 --world-model-set model.num_layers=16 --world-model-set model.num_heads=16 \
  --world-model-set model.ffn_dim=4096 > runs/big.out 2>&1 &   # big/main.log
python3 -m benchmarks.bench_grpo_reward_source run --workdir runs/mid --gpus 1 $C \
  --world-model-set model.dim=768 --world-model-set model.num_layers=12 --world-model-set model.num_heads=12 \
  --world-model-set model.ffn_dim=3072 > runs/mid.out 2>&1 &   # mid/main.log
wait
# the record: each work dir's logs, configs, stage records, metrics and GRPO history (no weights)
