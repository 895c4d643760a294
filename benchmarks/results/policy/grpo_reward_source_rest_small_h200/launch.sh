# one H200 (16 CPU cores), 2026-11-29. The policy is the one committed with grpo_rest_h12_seeds_small_2xh200.
# The launcher below was stopped about 1,390 s after its start, once both runs had started; they ran on to step 20.
# A second launch of the same command with --arms exec (main_relaunch.log), meant to restart a run that was thought
# stopped, started a second exec_s0 in the same work dir before the first had finished. It evaluated the
# starting policy (exec_s0.log's second "eval step 0" line: 0.710, sampled 0.520, proprio masked 0.520, against the
# first run's 0.720, 0.440 and 0.510 for the same policy and key: the runs did not use --deterministic) and was
# stopped before its first step. The first run finished its 20 steps and wrote its history, step times and curve
# last; they agree line by line with its progress lines in exec_s0.log, and they are the figures reported.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python -m benchmarks.bench_grpo_reward_source run --workdir runs/rs3 --policy $P --gpus 0 --seeds 0 \
    --arms gt,exec --horizon 12 --keyframe-fraction 0 --vae-variant vae8x --world-model-steps 12000 \
    --rollout-batch 64 --scale-by-std false --steps 20 --eval-every 10 --eval-episodes-per-task 10 \
    --deadline-s 1480 --grace-s 45
python -m benchmarks.bench_grpo_reward_source summary --workdir runs/rs3 --out runs/rs3/grpo_reward_source
python -m benchmarks.bench_grpo_reward_source closed-loop --run "12,000 steps, from the first frame" \
    runs/rs3/exec_s0/rl/grpo runs/rs3/exec_s0.log runs/rs3/pipeline/world_model/metrics.jsonl \
    --trajectories 512 --out runs/rs3/closed_loop.json
python -m benchmarks.bench_grpo_reward_source figure --workdir runs/rs3 --out benchmarks/results/policy/grpo_reward_source_rest_small_h200.png
