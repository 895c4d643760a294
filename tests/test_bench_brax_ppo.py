"""bench_brax_ppo's figure: brax's env steps per second of the PPO iterations that did not compile."""

import pytest

from benchmarks.bench_brax_ppo import steady_steps_per_s


def test_the_steady_rate_leaves_out_the_first_iteration_which_compiles():
    iterations = [{"steps_per_s": 3.0}, {"steps_per_s": 900.0}, {"steps_per_s": 1000.0}, {"steps_per_s": 1100.0}]
    assert steady_steps_per_s(iterations) == 1000.0


def test_one_iteration_has_no_steady_rate():
    with pytest.raises(ValueError, match="at least 2 PPO iterations"):
        steady_steps_per_s([{"steps_per_s": 5.0}])
