cd /work/main && PYTHONUNBUFFERED=1 python -m train.grpo --config sword:small --seed 0 --simulator env \
  --policy /tmp/exp/p/policy_d50.npz --demos /tmp/exp/pipe/data/demos.hdf5 \
  --workdir /tmp/exp/run --env-workers 2 --rl.env.backend=cpu \
  --rl.env.starts=keyframes --rl.env.proprio=missing \
  --rl.grpo.rollout_batch=16 --rl.grpo.group_size=8 --rl.grpo.minibatches=4 --rl.grpo.update_microbatch=8 \
  --rl.grpo.temperature=0.5 --rl.grpo.learning_rate=1e-4 \
  --rl.imagined.execute_steps=4 --rl.imagined.max_chunks=12 \
  --rl.grpo.eval_sampled=true \
  --rl.grpo.steps=20 --rl.grpo.eval_every=10 --rl.grpo.eval_episodes_per_task=10
