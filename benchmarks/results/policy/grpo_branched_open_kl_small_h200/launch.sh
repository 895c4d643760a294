#!/bin/bash
# Launched beside the 256-starts runs: see ../grpo_branched_open_b256_seeds_small_h200/launch.sh (run gv6 there).
# 64 open starts x 8, success alone, KL 0.04 to the starting policy (rl.grpo.kl_coef), seed 0; reached step 50.
