#!/bin/bash
# 2-core CPU (the C engine), 2026-11-29: how many of ground-truth GRPO's groups carry a signal at each rollout horizon?
# policy_d50 (the SFT command of ../closed_loop_small_h200/launch.sh), seed 0, keyframe starts from 50 expert
# demonstrations (5 per task, mean 46 actions), proprio missing, 4 actions a decision, T 0.5, 32 start states x 8,
# 2 GRPO steps per horizon; the evaluations (10 episodes each) only bracket the steps. Horizons 2 and 4 start from
# keyframes of every phase (keyframe_fraction 1.0), horizon 12 from the first half (the learned simulator's setting).
python -m train.gen_data --task all --episodes 5 --out /tmp/hz/demos.hdf5 --stop-at-success --resolution 128 --init-split train
for spec in "2 1.0" "4 1.0" "12 0.5"; do
  set -- $spec
  python -m train.grpo --config sword:small --seed 0 --simulator env \
    --policy runs/p/policy_d50.npz --demos /tmp/hz/demos.hdf5 --workdir /tmp/hz/h$1 --env-workers 2 --rl.env.backend=cpu \
    --rl.env.starts=keyframes --rl.env.proprio=missing --rl.grpo.rollout_batch=32 --rl.grpo.group_size=8 \
    --rl.grpo.minibatches=4 --rl.grpo.update_microbatch=8 --rl.grpo.temperature=0.5 --rl.grpo.learning_rate=1e-4 \
    --rl.imagined.execute_steps=4 --rl.imagined.max_chunks=$1 --rl.imagined.keyframe_fraction=$2 \
    --rl.grpo.steps=2 --rl.grpo.eval_every=100 --rl.grpo.eval_episodes_per_task=1 > /tmp/hz/h$1.log 2>&1
done
