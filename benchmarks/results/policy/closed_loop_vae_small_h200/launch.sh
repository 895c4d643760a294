#!/bin/bash
# One H200, 2026-11-28: does the world model move the scene, and what does the VAE's round trip cost the policy?
# policy_d50 (the SFT command of ../closed_loop_small_h200/launch.sh, carried in); Sword's small pipeline with its
# world model trained 12,000 steps (VAE 1,000 steps, detector); the view probe (real, lag_1, vae: 20 episodes a
# task each) once the VAE existed, beside the world model's training; then, beside each other on the same GPU,
# the exec arm of benchmarks.bench_grpo_reward_source (the world model's frames, the real outcome of their
# actions; 64 x 8 trajectories a step, closed-loop record of the first 64, seed 0, 100 MJX episodes per
# evaluation) for 2 steps at the config's 5 Euler steps per chunk, and for 1 step at 20 (--flow.sample_steps=20).
# environment: mujoco 4.0.0, mujoco-mjx, brax and gymnasium on PYTHONPATH, NCCL_NVLS_ENABLE=0,
# JAX_COMPILATION_CACHE_DIR set
R=/tmp/runs/rs; P=$R/pipeline; POL=/tmp/runs/p/policy_d50.npz
mkdir -p $R
log() { echo "[d2 $(date +%T)] $*" >> $R/main.log; }
nvidia-smi --query-gpu=name,memory.total --format=csv > $R/gpu.txt
[ -f $POL ] || { log no policy; exit 1; }
PIPE="--config sword:small --seed 0 --stop-after reward_model --skip probe,evaluate --parallel 2 \
 --data.policy_rollouts_per_task=20 --rl.sft.episodes_per_task=20 --rl.sft.init=$POL --vae.train_steps=1000 --sim.backend=cpu"
log pipeline start
XLA_PYTHON_CLIENT_MEM_FRACTION=0.55 python3 -m train.pipeline $PIPE --workdir $P --trainer.steps=12000 > $R/pipeline.log 2>&1 &
PA=$!
( while [ ! -f $P/stages/vae.json ]; do kill -0 $PA 2>/dev/null || exit 1; sleep 5; done
  log view start
  XLA_PYTHON_CLIENT_MEM_FRACTION=0.25 python3 -m benchmarks.bench_policy_view --config sword:small --policy $POL \
    --views real,lag_1,vae --vae $P/vae_run/vae --episodes-per-task 20 --out $R/view_vae \
    --rl.grpo.temperature=0.5 --rl.imagined.execute_steps=4 > $R/view.log 2>&1
  log view done rc $?
) &
wait $PA; log pipeline done rc $?
G="--config sword:small --simulator world_model --vae $P/vae_run/vae --reward $P/rl/reward_model \
 --demos $P/data/demos.hdf5 --policy $POL --rl.env.backend=mjx --rl.grpo.rollout_batch=64 --rl.grpo.group_size=8 \
 --rl.grpo.minibatches=4 --rl.grpo.update_microbatch=8 --rl.grpo.temperature=0.5 --rl.grpo.learning_rate=1e-4 \
 --rl.grpo.eval_episodes_per_task=10 --rl.imagined.execute_steps=4 --rl.imagined.max_chunks=12 \
 --rl.imagined.shared_group_noise=true --rl.imagined.eval_replay_episodes=0 --rl.imagined.reward=executed \
 --rl.grpo.steps=2 --rl.grpo.eval_every=100 --seed 0"
log exec12k start
XLA_PYTHON_CLIENT_MEM_FRACTION=0.3 python3 -m train.grpo $G --world-model $P/world_model --workdir $R/exec12k > $R/exec12k.log 2>&1
log exec12k done rc $?
wait
log all done
# the 20-step run, started when the pipeline was done:
G="--config sword:small --simulator world_model --vae $P/vae_run/vae --reward $P/rl/reward_model \
 --demos $P/data/demos.hdf5 --policy $POL --rl.env.backend=mjx --rl.grpo.rollout_batch=64 --rl.grpo.group_size=8 \
 --rl.grpo.minibatches=4 --rl.grpo.update_microbatch=8 --rl.grpo.temperature=0.5 --rl.grpo.learning_rate=1e-4 \
 --rl.grpo.eval_episodes_per_task=10 --rl.imagined.execute_steps=4 --rl.imagined.max_chunks=12 \
 --rl.imagined.shared_group_noise=true --rl.imagined.eval_replay_episodes=0 --rl.imagined.reward=executed \
 --rl.grpo.steps=1 --rl.grpo.eval_every=100 --seed 0 --flow.sample_steps=20"
# log exec12k_s20 start
XLA_PYTHON_CLIENT_MEM_FRACTION=0.3 python3 -m train.grpo $G --world-model $P/world_model --workdir $R/exec12k_s20 > $R/exec12k_s20.log 2>&1
# log exec12k_s20 done rc $?
