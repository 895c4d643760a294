#!/bin/bash
# one H200 with 16 CPU cores, 2026-11-29: success alone at 256 open starts x 8 with 12-decision rollouts (48 actions),
# seeds 0-2, centred advantages, XLA's deterministic GPU ops. 1,100 s deadline with 240 s grace: at the deadline every
# run was asked to stop and evaluated the step it was on (15 of 30 for all three). Beside them on the same GPU, the
# evaluation's repeatability (eval_repeat/): two repeats of the same MJX evaluation of policy_d50 with deterministic
# ops (while the three runs trained), then two plain ones (after the runs had stopped): their times are not a ratio.
C="--policy runs/p/policy_d50.npz --gpus 0 --arms success --horizon 12 --value-episodes 512 --value-steps 2000
   --scale-by-std false --branch-starts open --steps 30 --eval-every 15 --deadline-s 1100 --grace-s 240 --deterministic"
python3 -m benchmarks.bench_grpo_value run --workdir runs/gv8 $C --seeds 0,1,2 --rollout-batch 256 &
( E="--policy runs/p/policy_d50.npz --repeats 2 --rl.grpo.temperature=0.5 --rl.env.proprio=missing"
  export XLA_PYTHON_CLIENT_PREALLOCATE=false XLA_PYTHON_CLIENT_MEM_FRACTION=0.1
  python3 -m benchmarks.bench_eval_repeat --out runs/gv8/er_det --deterministic $E
  python3 -m benchmarks.bench_eval_repeat --out runs/gv8/er $E ) &
wait
python3 -m benchmarks.bench_grpo_value summary --workdir runs/gv8 --out runs/gv8/grpo_value --record --record-as open_h12
python3 -m benchmarks.bench_eval_repeat --from runs/gv8/er_det/eval_repeat.json --record
