#!/bin/bash
# 2-core CPU (the C engine), 2026-11-30: ground-truth GRPO in the setting of grpo_reward_source_branched_small_2xh200,
# to read what reality pays rollouts of the same length on real frames: policy_d50, keyframe starts from every phase
# of 200 expert demonstrations (20 per task, training initial states), 2 decisions of 8 actions, proprio missing,
# T 0.5, 32 start states x 8, centred advantages, 5 GRPO steps per seed; the evaluations (10 episodes) only bracket
# the steps.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python -m train.gen_data --task all --episodes 20 --out /tmp/hz/demos.hdf5 --stop-at-success --resolution 128 --init-split train
for seed in 0 1 2; do
  python -m train.grpo --config sword:small --seed $seed --simulator env \
    --policy $P --demos /tmp/hz/demos.hdf5 --workdir /tmp/hz/s$seed --env-workers 2 --rl.env.backend=cpu \
    --rl.env.starts=keyframes --rl.env.proprio=missing --rl.grpo.rollout_batch=32 --rl.grpo.group_size=8 \
    --rl.grpo.minibatches=4 --rl.grpo.update_microbatch=8 --rl.grpo.temperature=0.5 --rl.grpo.learning_rate=1e-4 \
    --rl.grpo.scale_by_std=false --rl.imagined.execute_steps=8 --rl.imagined.max_chunks=2 \
    --rl.imagined.keyframe_fraction=1.0 --rl.grpo.steps=5 --rl.grpo.eval_every=100 \
    --rl.grpo.eval_episodes_per_task=1 > /tmp/hz/s$seed.log 2>&1
done
