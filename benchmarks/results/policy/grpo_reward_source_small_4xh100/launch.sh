# 4 x H100 of one host, 2026-11-28: the reward-source experiment as first launched (what
# benchmarks.bench_grpo_reward_source now runs as one command). policy_d50 re-made by
# `python -m benchmarks.bench_policy sft --config sword:small --out /tmp/runs/p --demos-per-task 50 --execute ens`
# (one H100; greedy with ensembling 0.704 [0.663, 0.742] on 500 episodes). This job ran in the process group of
# the shell that started it and ended with it: the ground-truth arm stopped after its step-10 evaluation and the
# pipeline inside its latents stage, before any world-model run started.
# phase 1: Sword's small pipeline on GPU 0; ground-truth GRPO in the learned simulator's setting (32 x 8) on GPUs 1-3
# phase 2: GRPO in the world model, paid by the detector or by executing the imagined actions on MJX
R=/tmp/runs/x; mkdir -p $R
STEPS=${STEPS:-40}
P=$R/pipeline; POL=/tmp/runs/p/policy_d50.npz
PIPE="--config sword:small --seed 0 --workdir $P --skip probe,evaluate --parallel 2 --data.policy_rollouts_per_task=20 \
 --rl.sft.episodes_per_task=20 --rl.sft.init=$POL --vae.train_steps=1000 --trainer.steps=3000 --sim.backend=cpu"
nvidia-smi --query-gpu=name,memory.total --format=csv > $R/gpu.txt
(
 CUDA_VISIBLE_DEVICES=0 python3 -m train.pipeline $PIPE --stop-after data > $R/pipeline.log 2>&1 || exit 1
 CUDA_VISIBLE_DEVICES=1,2,3 python3 -m benchmarks.bench_policy grpo-seeds --config sword:small --out $R/gt --policy $POL \
   --seeds 0,1,2 --gpus 1,2,3 --demos $P/data/demos.hdf5 --rl.env.backend=mjx --rl.grpo.rollout_batch=32 \
   --rl.grpo.group_size=8 --rl.grpo.minibatches=4 --rl.grpo.max_sample_rounds=1 --rl.grpo.update_microbatch=8 \
   --rl.grpo.temperature=0.5 --rl.grpo.learning_rate=1e-4 --rl.grpo.eval_every=10 --rl.grpo.eval_sampled=true \
   --rl.grpo.steps=$STEPS --rl.imagined.execute_steps=4 --rl.imagined.max_chunks=12 --rl.env.starts=keyframes \
   --rl.env.proprio=missing > $R/gt.log 2>&1 &
 CUDA_VISIBLE_DEVICES=0 python3 -m train.pipeline $PIPE --stop-after reward_model >> $R/pipeline.log 2>&1 || exit 1
 touch $R/pipeline.done
 G="--config sword:small --simulator world_model --world-model $P/world_model --vae $P/vae_run/vae \
  --reward $P/rl/reward_model --demos $P/data/demos.hdf5 --policy $POL --rl.env.backend=mjx --rl.grpo.rollout_batch=32 \
  --rl.grpo.group_size=8 --rl.grpo.minibatches=4 --rl.grpo.update_microbatch=8 --rl.grpo.temperature=0.5 \
  --rl.grpo.learning_rate=1e-4 --rl.grpo.eval_episodes_per_task=50 --rl.imagined.execute_steps=4 \
  --rl.imagined.max_chunks=12 --rl.imagined.shared_group_noise=true --rl.imagined.eval_replay_episodes=0 \
  --rl.grpo.steps=$STEPS --rl.grpo.eval_every=10"
 run() { # name gpu seed [overrides]
   local n=$1 g=$2 s=$3; shift 3
   CUDA_VISIBLE_DEVICES=$g XLA_PYTHON_CLIENT_MEM_FRACTION=0.45 python3 -m train.grpo $G --seed $s \
     --workdir $R/$n "$@" > $R/$n.log 2>&1 &
 }
 run exec_s0 0 0 --rl.imagined.reward=executed
 run det_s0 1 0
 run exec_s1 2 1 --rl.imagined.reward=executed
 run det_s1 2 1
 run exec_s2 3 2 --rl.imagined.reward=executed
 run det_s2 3 2
 wait
 touch $R/all.done
) > $R/go.log 2>&1 < /dev/null &
echo launched
