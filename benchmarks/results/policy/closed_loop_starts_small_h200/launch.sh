# One H200, 2026-12-02. Step 1 (times.txt 'start' .. first 'all done'): one small pipeline with the state probe, the
# start context on its VAE while the world model trains, then the closed loop from window and prefix starts.
# Step 2: a world model of 10,000 steps on the same latents (--adopt), the closed loop from prefix starts. Step 3:
# that world model with 10 sampler steps and with noise scale 0. Run from the repository root, W a scratch folder.

set -o pipefail
W=${W:-runs/sl}; mkdir -p $W
export XLA_PYTHON_CLIENT_PREALLOCATE=false
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
V="--vae.dim_mult=1,4,4 --vae.temporal_downsample=true,true"
t0=$(date +%s)
echo "start $(date -u +%FT%TZ)" > $W/times.txt
nvidia-smi --query-gpu=name,memory.total --format=csv > $W/gpu.txt
( while [ ! -f $W/pipeline/stages/vae.json ]; do sleep 5; done
  t=$(date +%s)
  python3 -m benchmarks.bench_start_latents --config sword:small --vae $W/pipeline/vae_run/vae \
      --episodes $W/pipeline/data/demos.hdf5 $V --out $W/sl > $W/sl.log 2>&1
  echo "start_latents rc $? $(( $(date +%s)-t )) s (at $(( $(date +%s)-t0 )) s)" >> $W/times.txt ) &
python3 -m train.pipeline --config sword:small --seed 0 --workdir $W/pipeline --stop-after reward_model \
    --skip evaluate --parallel 2 --data.policy_rollouts_per_task=10 --rl.sft.episodes_per_task=20 \
    --rl.sft.init=$P --vae.train_steps=600 --trainer.steps=5000 --sim.backend=cpu $V > $W/pipeline.log 2>&1
echo "pipeline rc $? $(( $(date +%s)-t0 )) s" >> $W/times.txt
t=$(date +%s)
python3 -m benchmarks.bench_closed_loop --pipeline $W/pipeline --policy $P --batches 1 --out $W/loop \
    --probe $W/pipeline/probe/probe.npz --variant w=rl.imagined.start_encoding=window \
    --variant p=rl.imagined.start_encoding=prefix --config sword:small --seed 0 $V \
    --rl.grpo.group_size=8 --rl.grpo.temperature=0.5 --rl.grpo.rollout_batch=64 --rl.imagined.execute_steps=4 \
    --rl.imagined.max_chunks=12 --rl.imagined.keyframe_fraction=0.0 --rl.imagined.shared_group_noise=true > $W/loop.log 2>&1
echo "loop rc $? $(( $(date +%s)-t )) s" >> $W/times.txt
wait
echo "all done $(( $(date +%s)-t0 )) s" >> $W/times.txt

# step 2
t0=$(date +%s)
python3 -m train.pipeline --config sword:small --seed 0 --workdir $W/long --adopt $W/pipeline --only world_model \
    --data.policy_rollouts_per_task=10 --rl.sft.episodes_per_task=20 --rl.sft.init=$P --vae.train_steps=600 \
    --trainer.steps=10000 --sim.backend=cpu $V > $W/long.log 2>&1
echo "long rc $? $(( $(date +%s)-t0 )) s" >> $W/times2.txt
t=$(date +%s)
python3 -m benchmarks.bench_closed_loop --pipeline $W/pipeline --world-model $W/long --policy $P --batches 1 --out $W/loop_long \
    --probe $W/pipeline/probe/probe.npz --variant p=rl.imagined.start_encoding=prefix --no-real --config sword:small --seed 0 $V \
    --rl.grpo.group_size=8 --rl.grpo.temperature=0.5 --rl.grpo.rollout_batch=64 --rl.imagined.execute_steps=4 \
    --rl.imagined.max_chunks=12 --rl.imagined.keyframe_fraction=0.0 --rl.imagined.shared_group_noise=true > $W/loop_long.log 2>&1
echo "loop_long rc $? $(( $(date +%s)-t )) s" >> $W/times2.txt
echo "all done $(( $(date +%s)-t0 )) s" >> $W/times2.txt

# step 3
python3 -m benchmarks.bench_closed_loop --pipeline $W/pipeline --world-model $W/long --policy $P --batches 1 --out $W/loop_long2 \
    --probe $W/pipeline/probe/probe.npz --variant s10=rl.imagined.start_encoding=prefix,flow.sample_steps=10 \
    --variant n0=rl.imagined.start_encoding=prefix,flow.noise_scale=0 --no-real --config sword:small --seed 0 $V \
    --rl.grpo.group_size=8 --rl.grpo.temperature=0.5 --rl.grpo.rollout_batch=64 --rl.imagined.execute_steps=4 \
    --rl.imagined.max_chunks=12 --rl.imagined.keyframe_fraction=0.0 --rl.imagined.shared_group_noise=true
