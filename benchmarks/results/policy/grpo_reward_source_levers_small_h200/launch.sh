# one H200 (16 CPU cores), 2026-11-30. The policy is the one committed with grpo_rest_h12_seeds_small_2xh200.
# The levers against grpo_reward_source_rest_small_h200 (12,000 steps, no weight average, layers scanned): one world
# model of 20,000 steps keeping an EMA at 0.999 with its layers unrolled, read from its EMA weights by two exec runs
# on the same GPU: 12 decisions of 4 actions (this folder) and, sharing its pipeline, 6 decisions of 8 (chunk/).
# Both runs finished step 5 and its evaluation; the deadline's stop reached them after it, while they closed.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
W="--world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false"
C="--policy $P --gpus 0 --seeds 0 --arms exec --keyframe-fraction 0 --vae-variant vae8x --rollout-batch 64 \
   --scale-by-std false --steps 5 --eval-every 5 --eval-episodes-per-task 10 --grace-s 45"
python -m benchmarks.bench_grpo_reward_source run --workdir runs/rs4 $C $W --horizon 12 --world-model-steps 20000 \
    --deadline-s 1560 &
sleep 25   # then once runs/rs4/pipeline exists
python -m benchmarks.bench_grpo_reward_source run --workdir runs/rs4c --pipeline runs/rs4/pipeline $C $W --horizon 6 \
    --actions-per-decision 8 --deadline-s 1535
wait
python -m benchmarks.bench_grpo_reward_source summary --workdir runs/rs4 --out runs/rs4/grpo_reward_source
python -m benchmarks.bench_grpo_reward_source summary --workdir runs/rs4c --out runs/rs4/chunk/grpo_reward_source
# the three world-model runs over their first 5 steps (the 12,000-step one from grpo_reward_source_rest_small_h200)
python -m benchmarks.bench_grpo_reward_source closed-loop --first-steps 5 --decision-actions 4,4,8 \
    --run "12,000 steps, 4 actions a decision" runs/rs3/exec_s0/rl/grpo runs/rs3/exec_s0.log runs/rs3/pipeline/world_model/metrics.jsonl \
    --run "20,000 steps, EMA, 4 actions a decision" runs/rs4/exec_s0/rl/grpo runs/rs4/exec_s0.log runs/rs4/pipeline/world_model/metrics.jsonl \
    --run "20,000 steps, EMA, 8 actions a decision" runs/rs4c/exec_s0/rl/grpo runs/rs4c/exec_s0.log runs/rs4/pipeline/world_model/metrics.jsonl \
    --trajectories 512 --out runs/rs4/closed_loop.json
python -m benchmarks.bench_grpo_reward_source figure --closed-loop runs/rs4/closed_loop.json \
    --out benchmarks/results/policy/grpo_reward_source_levers_small_h200.png \
    --title "small world models (36.7 M, 8x VAE), seed 0, 64 starts x 8 a step from the first real frame, T 0.5, proprio masked, first 5 GRPO steps; one H200"
