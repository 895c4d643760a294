#!/bin/bash
# 2 x H200 of one host (32 CPU cores), 2026-11-30: what reality pays GRPO's training rollouts on real frames (gt) and
# on the 30,000-step world model's frames with their actions executed on MJX (exec), by horizon: 1, 2, 3, 4 and 6
# decisions of 8 actions from keyframes of every phase of the demonstrations, 64 starts x 8, T 0.5, proprio masked,
# centred advantages, 4 GRPO steps, seed 0; the evaluations (10 episodes) only bracket the steps. The world model,
# VAE and detector were read from the bundle of world_model_policy_split_30k_small_h200 (train.bundle unpack); the
# ten runs shared the two GPUs (h1, h2, h6 on GPU 0; h3, h4 on GPU 1).
# The demonstrations every horizon reads (the reward-source benchmark's data stage):
mkdir -p /tmp/runs/hz/data
python3 -m train.pipeline --config sword:small --seed 0 --workdir /tmp/runs/hz/data/pipeline --stop-after data \
  --skip probe,evaluate --parallel 2 --data.policy_rollouts_per_task=20 --rl.sft.episodes_per_task=20 \
  --rl.sft.init=/tmp/runs/p/policy_d50.npz --vae.train_steps=1000 --trainer.steps=3000 --sim.backend=cpu \
  --vae.dim_mult=1,4,4 --vae.temporal_downsample=true,true --trainer.ema_decay=0.999 --model.scan_layers=false \
  > /tmp/runs/hz/data.log 2>&1 &
R=/tmp/runs; H=$R/hz; mkdir -p $H; nvidia-smi --query-gpu=name,memory.total --format=csv > $H/gpu.txt
python3 -m train.bundle unpack /tmp/wm /tmp/bp > $H/unpack.log 2>&1 || { echo "hz rc unpack-failed" >> $H/hz.out; exit 1; }
common="--policy $R/p/policy_d50.npz --bundle /tmp/wm --vae-variant vae8x --world-model-set trainer.ema_decay=0.999
  --world-model-set model.scan_layers=false --seeds 0 --arms gt,exec --keyframe-fraction 1.0 --actions-per-decision 8
  --scale-by-std false --rollout-batch 64 --steps 4 --eval-every 100 --eval-episodes-per-task 1
  --deadline-s ${DEADLINE:-1300} --grace-s 30"
for spec in 1:0 2:0 6:0 3:1 4:1; do
  h=${spec%:*}; g=${spec#*:}
  pipe="--pipeline $H/data/pipeline"
  ( python3 -m benchmarks.bench_grpo_reward_source run --workdir $H/h$h $common --gpus $g --horizon $h $pipe \
      > $H/h$h.out 2>&1; echo "run rc $?" >> $H/h$h.out
    python3 -m benchmarks.bench_grpo_reward_source summary --workdir $H/h$h --out $H/h${h}_summary >> $H/h$h.out 2>&1
    echo "summary rc $?" >> $H/h$h.out ) &
  sleep 2
done
wait; echo "hz all done" >> $H/hz.out
python3 -m benchmarks.bench_grpo_reward_source horizons --workdirs $H/h1,$H/h2,$H/h3,$H/h4,$H/h6 --out $H/horizons
