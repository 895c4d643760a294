# phase 2: ground-truth GRPO on MJX in the learned simulator's setting, one part at a time, 3 seeds per arm
#   A: keyframe starts, 48 actions executed 4 at a time, proprio missing (the learned simulator's setting)
#   B: A with true proprio;  C: from rest as the ground-truth recipe, proprio missing
source .dev/env.sh
export XLA_PYTHON_CLIENT_PREALLOCATE=false
R=/tmp/runs/a44; mkdir -p $R /tmp/runs /tmp/demos
[ -f /tmp/runs/p/policy_d50.npz ] || tar xzf .dev/runs.tgz -C /tmp/runs p/policy_d50.npz
for t in 0 1 2 3 4 5 6 7 8 9; do
  python3 -m train.gen_data --task $t --episodes 20 --out /tmp/demos/demos_$t.hdf5 --resolution 128 --stop-at-success \
    --no-wrist --seed $t > /tmp/demos/gen_$t.log 2>&1 &
done; wait
ls /tmp/demos/*.hdf5 | wc -l
D=""; for t in 0 1 2 3 4 5 6 7 8 9; do D="$D --demos /tmp/demos/demos_$t.hdf5"; done
COMMON="--config sword:small --policy /tmp/runs/p/policy_d50.npz --seeds 0,1,2 --rl.env.backend=mjx \
 --rl.grpo.rollout_batch=64 --rl.grpo.group_size=8 --rl.grpo.minibatches=4 --rl.grpo.max_sample_rounds=2 \
 --rl.grpo.min_mixed_fraction=0.8 --rl.grpo.update_microbatch=8 --rl.grpo.temperature=0.5 --rl.grpo.learning_rate=1e-4 \
 --rl.grpo.eval_every=10 --rl.grpo.eval_sampled=true --rl.grpo.steps=${STEPS:-30} --rl.imagined.execute_steps=4 \
 --rl.imagined.max_chunks=12"
setsid nohup python3 -m benchmarks.bench_policy grpo-seeds --out $R/C $COMMON --gpus 0,0,1 --rl.env.proprio=missing \
  > $R/C.log 2>&1 < /dev/null &
setsid nohup python3 -m benchmarks.bench_policy grpo-seeds --out $R/A $COMMON --gpus 0,1,1 $D --rl.env.starts=keyframes \
  --rl.env.proprio=missing > $R/A.log 2>&1 < /dev/null &
setsid nohup python3 -m benchmarks.bench_policy grpo-seeds --out $R/B $COMMON --gpus 1,0,1 $D --rl.env.starts=keyframes \
  > $R/B.log 2>&1 < /dev/null &
echo launched
