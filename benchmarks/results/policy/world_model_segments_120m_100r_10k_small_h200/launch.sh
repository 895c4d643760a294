#!/bin/bash
# One H200 (16 CPU cores), 2026-12-02: where does the world model's error on the supervised policy's unseen rollouts
# lie, and does a model with both more parameters and more of the policy's data move it? small's pipeline as
# world_model_size_10k_small_2xh200/mid (seed 0, the 8x VAE, EMA 0.999, unrolled layers, a 768 x 12 world model of
# 120.0 M parameters, 10,000 steps) with 100 rollouts of the policy per task beside the 200 expert episodes instead
# of 20, and the trainer's per-segment record at the end (--trainer.eval_segments=true). The held-out policy
# rollouts (2 per task from the held-out initial states) and the fixed segments are the same as that run's.
P=$PWD/benchmarks/results/policy/grpo_rest_h12_seeds_small_2xh200/policy_d50/policy_d50.npz
W=/tmp/runs/mid100
python3 -m train.pipeline --config sword:small --seed 0 --workdir $W/pipeline --stop-after world_model \
  --skip probe,evaluate --parallel 2 --data.policy_rollouts_per_task=100 --rl.sft.episodes_per_task=20 \
  --rl.sft.init=$P --vae.train_steps=1000 --trainer.steps=10000 --sim.backend=cpu --vae.dim_mult=1,4,4 \
  --vae.temporal_downsample=true,true --trainer.ema_decay=0.999 --model.scan_layers=false \
  --data.policy_rollout_workers=12 --model.dim=768 --model.num_layers=12 --model.num_heads=12 --model.ffn_dim=3072 \
  --trainer.eval_segments=true > $W/pipeline.log 2>&1
# the held-out policy episodes' task, initial state, first success, rewards, actions and per-step stage (the recorded
# states restored on the C engine), in the latents stage's order (this record's policy_outcomes.npz: the same
# arrays, the first five read from the same file by an equivalent script, the stages by segment_errors.step_stages
# from its recorded states)
python3 -m benchmarks.segment_errors outcomes $W/pipeline/data/policy_heldout.hdf5 $W/policy_outcomes.npz
# (on the record, CPU) the per-segment errors joined with them: segments.json, report table world-model-segments
python3 -m benchmarks.segment_errors join --pipeline pipeline --outcomes policy=policy_outcomes.npz --out segments.json
# the record: the pipeline's configs, stage records, logs and world-model metrics (no weights or data)
