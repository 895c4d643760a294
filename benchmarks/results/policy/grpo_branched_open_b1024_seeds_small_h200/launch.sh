#!/bin/bash
# one H200 with 16 CPU cores, 2026-11-29: success alone at 1,024 open starts x 8, seeds 0-2, centred advantages.
# 1,120 s deadline with 240 s grace: at the deadline every run was asked to stop, evaluated its step in flight
# (19, 18 and 19 of 40) and checkpointed it. Beside them on the same GPU, the evaluation's repeatability
# (eval_repeat/): three repeats of the same MJX evaluation of policy_d50, then the same with XLA's deterministic
# ops; the deterministic one was cut off by the run's time limit after its second repeat (its log has both).
C="--policy runs/p/policy_d50.npz --gpus 0 --arms success --horizon 4 --value-episodes 512 --value-steps 2000
   --scale-by-std false --branch-starts open --steps 40 --eval-every 20 --deadline-s 1120 --grace-s 240"
python3 -m benchmarks.bench_grpo_value run --workdir runs/gv7 $C --seeds 0,1,2 --rollout-batch 1024 &
( E="--policy runs/p/policy_d50.npz --repeats 3 --rl.grpo.temperature=0.5 --rl.env.proprio=missing"
  export XLA_PYTHON_CLIENT_PREALLOCATE=false XLA_PYTHON_CLIENT_MEM_FRACTION=0.15
  python3 -m benchmarks.bench_eval_repeat --out runs/gv7/er $E
  python3 -m benchmarks.bench_eval_repeat --out runs/gv7/er_det --deterministic $E ) &
wait
python3 -m benchmarks.bench_grpo_value summary --workdir runs/gv7 --out runs/gv7/grpo_value --record --record-as open_b1024
python3 -m benchmarks.bench_eval_repeat --out runs/gv7/er --summary-only --record
