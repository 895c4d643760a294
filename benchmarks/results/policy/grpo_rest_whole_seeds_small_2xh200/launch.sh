#!/bin/bash
# These runs (rest_whole, GPU 1) were launched side by side with the 12-decision runs (rest_h12, GPU 0) by one
# script, which says the machine, the policy, the deadline and where each run stopped.
exec bash "$(dirname "$0")/../grpo_rest_h12_seeds_small_2xh200/launch.sh"
