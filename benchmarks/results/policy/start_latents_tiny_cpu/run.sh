# 2-core CPU, 2026-12-02: the tiny pipeline's data (2 tasks, one episode each, and the policy's rollouts), a tiny VAE
# trained 2,000 steps on its training episodes (605 s; its last logged loss 0.28), then
# the benchmark on the 8 episodes of its four files.
set -o pipefail
python -m train.pipeline --workdir runs/t/pipeline --stop-after reward_model --skip probe,evaluate,world_model
python -m train.train_vae --config sword:tiny --workdir runs/t/vae2k --episodes runs/t/pipeline/data/train.hdf5 \
    --vae.train_steps=2000
python -m benchmarks.bench_start_latents --config sword:tiny --vae runs/t/vae2k/vae \
    --episodes runs/t/pipeline/data/train.hdf5 --episodes runs/t/pipeline/data/heldout.hdf5 \
    --episodes runs/t/pipeline/data/policy_rollouts.hdf5 --episodes runs/t/pipeline/data/policy_heldout.hdf5 \
    --latents 1,2,3,6,12,20 --out runs/t/start_latents
