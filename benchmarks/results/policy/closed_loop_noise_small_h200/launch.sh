# one H200 (16 CPU cores), 2026-12-02: the pipeline (687 s) and then the benchmark (287 s), one process each.
# The world model is shorter-trained than table grpo-reward-source-rest's (5,000 steps, VAE 600 steps, 10 policy
# rollouts per task): the variants are compared with each other on it, not with the earlier tables.
set -o pipefail
W=runs/cl
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python3 -m train.pipeline --config sword:small --seed 0 --workdir $W/pipeline --stop-after reward_model \
    --skip probe,evaluate --parallel 2 --data.policy_rollouts_per_task=10 --rl.sft.episodes_per_task=20 \
    --rl.sft.init=$P --vae.train_steps=600 --trainer.steps=5000 --sim.backend=cpu --vae.dim_mult=1,4,4 \
    --vae.temporal_downsample=true,true > $W/pipeline.log 2>&1
python3 -m benchmarks.bench_closed_loop --pipeline $W/pipeline --policy $P --batches 1 --out $W/loop \
    --variant n1=flow.noise_scale=1 --variant n0=flow.noise_scale=0 --variant n05=flow.noise_scale=0.5 \
    --config sword:small --seed 0 --vae.dim_mult=1,4,4 --vae.temporal_downsample=true,true \
    --rl.grpo.group_size=8 --rl.grpo.temperature=0.5 --rl.grpo.rollout_batch=64 --rl.imagined.execute_steps=4 \
    --rl.imagined.max_chunks=12 --rl.imagined.keyframe_fraction=0.0 --rl.imagined.shared_group_noise=true \
    > $W/loop.log 2>&1
