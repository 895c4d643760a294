# 2 x H200 of one host (32 CPU cores), 2026-11-30. GRPO in the world model of world_model_policy_split_30k_small_h200
# (30,000 steps, EMA 0.999, 8x VAE; read from its 14-part bundle, `python -m train.bundle unpack`), rolled out 2
# decisions of 8 actions from keyframes of every phase of the demonstrations, 32 starts x 8, the exec arm (the imagined
# actions executed on MJX for the reward) and the det arm (the detector's reward), seeds 0-2, the three runs of an arm
# on one GPU. Only the pipeline's data stage ran (the keyframes' demonstrations). All six runs finished their 30 steps
# and their step-30 evaluations (500 MJX episodes each) within the deadline.
P=benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
python -m train.bundle unpack runs/wm runs/bundle_parts
python -m benchmarks.bench_grpo_reward_source run --workdir runs/rs10 --policy $P \
    --bundle runs/wm --vae-variant vae8x --world-model-set trainer.ema_decay=0.999 \
    --world-model-set model.scan_layers=false --gpus 0,1 --seeds 0,1,2 --arms exec,det --horizon 2 \
    --keyframe-fraction 1.0 --actions-per-decision 8 --scale-by-std false --steps 30 --eval-every 10 \
    --eval-episodes-per-task 50 --deadline-s 1400 --grace-s 45
python -m benchmarks.bench_grpo_reward_source summary --workdir runs/rs10 --out runs/rs10/grpo_reward_source
python -m benchmarks.bench_grpo_reward_source figure --workdir runs/rs10 \
    --out benchmarks/results/policy/grpo_reward_source_branched_small_2xh200.png
