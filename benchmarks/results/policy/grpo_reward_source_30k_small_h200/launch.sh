# one H200 (16 CPU cores), 2026-11-30. The policy is the one committed with grpo_rest_h12_seeds_small_2xh200.
# After grpo_reward_source_levers_small_h200: the world model trained 30,000 steps (against 20,000) with the same
# EMA at 0.999 and unrolled layers, read from its EMA weights at 8 actions a decision, for 10 GRPO steps.
# The run finished its 10 steps and their evaluation within the deadline.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python -m benchmarks.bench_grpo_reward_source run --workdir runs/rs5 --policy $P --gpus 0 --seeds 0 \
    --arms exec --horizon 6 --actions-per-decision 8 --keyframe-fraction 0 --vae-variant vae8x \
    --world-model-steps 30000 --world-model-set trainer.ema_decay=0.999 \
    --world-model-set model.scan_layers=false --rollout-batch 64 --scale-by-std false --steps 10 \
    --eval-every 10 --eval-episodes-per-task 10 --grace-s 45 --deadline-s 1640
python -m benchmarks.bench_grpo_reward_source summary --workdir runs/rs5 --out runs/rs5/grpo_reward_source
# beside the levers' 20,000-step world model at 8 actions a decision, over the first 5 steps
L=benchmarks/results/policy/grpo_reward_source_levers_small_h200
python -m benchmarks.bench_grpo_reward_source closed-loop --first-steps 5 --decision-actions 8,8 \
    --run "20,000 steps, EMA, 8 actions a decision" $L/chunk/exec_s0/rl/grpo $L/chunk/exec_s0.log $L/pipeline/world_model/metrics.jsonl \
    --run "30,000 steps, EMA, 8 actions a decision" runs/rs5/exec_s0/rl/grpo runs/rs5/exec_s0.log runs/rs5/pipeline/world_model/metrics.jsonl \
    --trajectories 512 --out runs/rs5/closed_loop.json
python -m benchmarks.bench_grpo_reward_source figure --closed-loop runs/rs5/closed_loop.json \
    --out benchmarks/results/policy/grpo_reward_source_30k_small_h200.png \
    --title "small world models (36.7 M, 8x VAE), seed 0, 64 starts x 8 a step from the first real frame, T 0.5, proprio masked, 8 actions a decision, first 5 GRPO steps; one H200"
