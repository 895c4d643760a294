# one H200 (16 CPU cores), 2026-12-02: four world models on one pipeline's data, VAE and latents, trained side by
# side on the GPU, then GRPO's closed loop measured in each (the same starts and keys). Shared stages 543 s, the
# four world models 389-523 s beside each other, the closed loops 226-228 s three at a time (b's first attempt ran
# out of GPU memory beside the others, loop_first_attempt_oom.log; it ran again alone, 68 s).
set -o pipefail
W=runs/clw
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
C="--config sword:small --seed 0 --sim.backend=cpu --data.policy_rollouts_per_task=10 --rl.sft.episodes_per_task=20
   --rl.sft.init=$P --vae.train_steps=600 --trainer.steps=5000 --vae.dim_mult=1,4,4 --vae.temporal_downsample=true,true"
# the shared stages (data, VAE, latents, policy rollouts, detector), no world model yet
python3 -m train.pipeline $C --workdir $W/a --stop-after reward_model --skip probe,evaluate,world_model --parallel 2 \
    > $W/shared.log 2>&1
# a: DLB as configured (one-step cache writes); b: DLB writing the flow sampler's own samples (5 Euler steps, as
# inference); c: teacher forcing (DLB off); d: a with WoVR's context noise (std 0.1 on the context latents)
declare -A X=([a]="" [b]="--cache.write_source=sampler" [c]="--cache.enabled=false" [d]="--flow.context_noise=0.1")
for v in a b c d; do
  adopt=""; [ $v != a ] && adopt="--adopt $W/a"
  XLA_PYTHON_CLIENT_PREALLOCATE=false python3 -m train.pipeline $C ${X[$v]} --workdir $W/$v $adopt --only world_model \
      > $W/wm_$v.log 2>&1 &
done
wait
L="--config sword:small --seed 0 --vae.dim_mult=1,4,4 --vae.temporal_downsample=true,true --rl.grpo.group_size=8
   --rl.grpo.temperature=0.5 --rl.grpo.rollout_batch=64 --rl.imagined.execute_steps=4 --rl.imagined.max_chunks=12
   --rl.imagined.keyframe_fraction=0.0 --rl.imagined.shared_group_noise=true"
for v in a b c d; do
  real="--no-real"; [ $v = a ] && real=""
  XLA_PYTHON_CLIENT_PREALLOCATE=false python3 -m benchmarks.bench_closed_loop --pipeline $W/a --world-model $W/$v \
      --policy $P --batches 1 --out $W/loop_$v --variant n1=flow.noise_scale=1 $real $L > $W/loop_$v.log 2>&1 &
done
wait
