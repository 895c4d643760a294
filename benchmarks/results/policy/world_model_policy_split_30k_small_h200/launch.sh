# one H200 (16 CPU cores), 2026-11-30. The policy is the one committed with grpo_rest_h12_seeds_small_2xh200.
# The 30,000-step world model of world_model_heldout_30k_small_h200 again (EMA 0.999, unrolled layers), its trainer
# now also measuring a third split: 2 x 32 fixed segments of 20 held-out rollouts of the supervised policy (2 per
# task, from the held-out initial states, never trained on). Once the pipeline's stages were done, its inference
# weights were packed into a bundle of 14 parts (bundle.json: sizes and SHA-256 of each) for later machines.
# The pipeline took 1,148 s after a 96 s data stage, so GRPO logged its step-0 evaluation only.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
C="--policy $P --gpus 0 --seeds 0 --arms exec --keyframe-fraction 0 --vae-variant vae8x --rollout-batch 64
   --scale-by-std false --steps 20 --eval-every 10 --eval-episodes-per-task 10 --grace-s 45 --horizon 6
   --actions-per-decision 8 --world-model-steps 30000
   --world-model-set trainer.ema_decay=0.999 --world-model-set model.scan_layers=false"
python -m benchmarks.bench_grpo_reward_source run --workdir runs/rs7 $C --deadline-s 1500 > runs/rs7.out 2>&1 &
A=$!
for i in $(seq 400); do
  [ -f runs/rs7/pipeline/stages/reward_model.json ] && [ -f runs/rs7/pipeline/stages/world_model.json ] && break
  sleep 5
done
JAX_PLATFORMS=cpu python -m train.bundle pack runs/rs7/pipeline runs/bundle --part-mib 15.9
wait $A
python -m benchmarks.bench_grpo_reward_source figure --world-model runs/rs7/pipeline/world_model/metrics.jsonl \
    --out benchmarks/results/policy/world_model_policy_split_30k_small_h200.png \
    --title "small world model (36.7 M, 8x VAE), seed 0, EMA 0.999; 64 segments per split every 1,000 steps; one H200"
