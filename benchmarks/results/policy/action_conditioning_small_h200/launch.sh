# One H200, 2026-12-02. One small pipeline with the state probe; beside its world model, two more on the same latents
# (--adopt): action dropout 0.1 (the unconditional branch action guidance needs) and no DLB cache; then the closed
# loop of each from the same 64 starts from rest x 8 and keys. Afterwards the pipeline's evaluation (psnr, ssim and
# the probe, open loop on held-out expert episodes). Run from the repository root; W a scratch folder.
set -o pipefail
W=${W:-runs/ac}; mkdir -p $W
export XLA_PYTHON_CLIENT_PREALLOCATE=false
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
V="--vae.dim_mult=1,4,4 --vae.temporal_downsample=true,true"
C="--data.policy_rollouts_per_task=10 --rl.sft.episodes_per_task=20 --rl.sft.init=$P --vae.train_steps=600 --trainer.steps=5000 --sim.backend=cpu $V"
G="--rl.grpo.group_size=8 --rl.grpo.temperature=0.5 --rl.grpo.rollout_batch=64 --rl.imagined.execute_steps=4 --rl.imagined.max_chunks=12 --rl.imagined.keyframe_fraction=0.0 --rl.imagined.shared_group_noise=true"
t0=$(date +%s)
echo "start $(date -u +%FT%TZ)" > $W/times.txt
nvidia-smi --query-gpu=name,memory.total --format=csv > $W/gpu.txt
variant() {  # name, overrides
  while [ ! -f $W/pipeline/stages/latents.json ]; do sleep 5; done
  t=$(date +%s)
  python3 -m train.pipeline --config sword:small --seed 0 --workdir $W/$1 --adopt $W/pipeline --only world_model $C $2 > $W/$1.log 2>&1
  echo "wm_$1 rc $? $(( $(date +%s)-t )) s (at $(( $(date +%s)-t0 )) s)" >> $W/times.txt
}
variant ad "--flow.action_dropout=0.1" &
variant nodlb "--cache.enabled=false" &
python3 -m train.pipeline --config sword:small --seed 0 --workdir $W/pipeline --stop-after reward_model \
    --parallel 2 --eval.metrics=psnr,ssim --eval.floor_metrics=psnr,ssim --eval.num_episodes=50 $C > $W/pipeline.log 2>&1
echo "pipeline rc $? $(( $(date +%s)-t0 )) s" >> $W/times.txt
t=$(date +%s)
python3 -m benchmarks.bench_closed_loop --pipeline $W/pipeline --policy $P --batches 1 --out $W/loop_base --frames 4 \
    --probe $W/pipeline/probe/probe.npz --variant p=rl.imagined.start_encoding=prefix --config sword:small --seed 0 $V $G > $W/loop_base.log 2>&1
echo "loop_base rc $? $(( $(date +%s)-t )) s (at $(( $(date +%s)-t0 )) s)" >> $W/times.txt
wait
t=$(date +%s)
python3 -m benchmarks.bench_closed_loop --pipeline $W/pipeline --world-model $W/ad --policy $P --batches 1 --out $W/loop_ad --no-real \
    --probe $W/pipeline/probe/probe.npz --variant g1=rl.imagined.start_encoding=prefix \
    --variant g2=rl.imagined.start_encoding=prefix,flow.guidance_scale=2 --variant g3=rl.imagined.start_encoding=prefix,flow.guidance_scale=3 \
    --config sword:small --seed 0 $V $G > $W/loop_ad.log 2>&1 &
python3 -m benchmarks.bench_closed_loop --pipeline $W/pipeline --world-model $W/nodlb --policy $P --batches 1 --out $W/loop_nodlb --no-real \
    --probe $W/pipeline/probe/probe.npz --variant p=rl.imagined.start_encoding=prefix \
    --config sword:small --seed 0 $V $G > $W/loop_nodlb.log 2>&1
wait
echo "loops rc $? $(( $(date +%s)-t )) s" >> $W/times.txt
echo "all done $(( $(date +%s)-t0 )) s" >> $W/times.txt

# the evaluation of the pipeline's world model; the same for the other two was refused (times.txt: ev_ad, ev_nodlb
# 1): their work dirs were made with the default evaluation settings
python3 -m train.pipeline --config sword:small --seed 0 --workdir $W/pipeline --only evaluate $C \
    --eval.metrics=psnr,ssim --eval.floor_metrics=psnr,ssim --eval.num_episodes=50 > $W/ev_base.log 2>&1
