# one H200 (16 CPU cores), 2026-11-30. The policy is the one committed with grpo_rest_h12_seeds_small_2xh200.
# The 30,000-step world model of grpo_reward_source_30k_small_h200 again (EMA 0.999, unrolled layers), its trainer
# now measuring 2 x 32 fixed held-out and as many training segments every 1,000 steps (sampler at 5 and 20 Euler
# steps). Two GRPO runs read it: at inference's 5 Euler steps, and (sampler20/) at 20. The pipeline took 1,254 s,
# so neither run took a GRPO step before the deadline: each logged its step-0 evaluation only.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
C="--policy $P --gpus 0 --seeds 0 --arms exec --keyframe-fraction 0 --vae-variant vae8x --rollout-batch 64
   --scale-by-std false --steps 5 --eval-every 5 --eval-episodes-per-task 10 --grace-s 45 --horizon 6
   --actions-per-decision 8 --world-model-steps 30000
   --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false"
python -m benchmarks.bench_grpo_reward_source run --workdir runs/rs6 $C --deadline-s 1640 > runs/rs6.out 2>&1 &
A=$!
sleep 25; while [ ! -d runs/rs6/pipeline ]; do sleep 5; done
python -m benchmarks.bench_grpo_reward_source run --workdir runs/rs6s --pipeline runs/rs6/pipeline $C \
    --world-model-set flow.sample_steps=20 --deadline-s 1615 > runs/rs6s.out 2>&1
wait $A
python -m benchmarks.bench_grpo_reward_source figure --world-model runs/rs6/pipeline/world_model/metrics.jsonl \
    --out benchmarks/results/policy/world_model_heldout_30k_small_h200.png \
    --title "small world model (36.7 M, 8x VAE), seed 0, 30,000 steps of 32 segments, EMA 0.999; 64 held-out and 64 training segments every 1,000 steps; one H200"
