"""The exploitation guard of GRPO in a learned simulator (sword_jax.rl.sim_guard) and its rollback in the
GRPO loop: judged verdicts, the rollback restoring the last passing policy and optimizer state, exact resume."""

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import grpo
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, RLConfig
from sword_jax.rl.grpo_loop import grpo_run_id, train_grpo
from sword_jax.rl.sim_guard import FalseSuccessGuard


def _replay(rate: float, failures: int = 50) -> dict:
    return {"false_success": {"rate": rate, "ci95": [0.0, 1.0], "of": failures}}


def test_guard_sets_its_baseline_from_the_first_judged_replay_and_trips_only_past_the_margin():
    guard = FalseSuccessGuard(0.1, min_failures=20)
    assert not guard.observe(None).trip and guard.baseline is None  # an evaluation without a replay
    few = guard.observe(_replay(0.9, failures=5))
    assert not few.trip and guard.baseline is None and "not judged" in few.reason
    assert not guard.observe(_replay(0.12)).trip and guard.baseline == pytest.approx(0.12)
    assert not guard.observe(_replay(0.22)).trip  # at the margin: passes
    tripped = guard.observe(_replay(0.23))
    assert tripped.trip and tripped.baseline == pytest.approx(0.12) and "> baseline 0.120" in tripped.reason
    assert not guard.observe(_replay(0.9, failures=19)).trip  # too few failures to judge
    for bad in ({"margin": 0.0}, {"margin": 1.0}, {"margin": 0.1, "min_failures": 0}):
        with pytest.raises(ValueError, match="FalseSuccessGuard"):
            FalseSuccessGuard(**bad)
    with pytest.raises(ValueError, match="guard_margin"):
        RLConfig(imagined=ImaginedConfig(guard_margin=1.5)).validate()


def _rl(steps: int, margin: float) -> RLConfig:
    return RLConfig(grpo=GRPOConfig(steps=steps, eval_every=2), imagined=ImaginedConfig(guard_margin=margin))


@jax.jit
def _step(state, batch, key):
    """Adds 1 to the parameter and counts the steps in a stand-in optimizer state."""
    params = {"w": state.params["w"] + 1.0}
    return state.replace(params=params, opt_state=state.opt_state + 1, step=state.step + 1), {"loss": params["w"]}


def _run(workdir, rl, log=lambda line: None):
    state = grpo.init_state({"w": jnp.zeros((), jnp.float32)}, rl)
    state = state.replace(opt_state=jnp.zeros((), jnp.int32))

    def evaluate(done, params):  # the simulator is exploited once w reaches 4: false success 0.1 -> 0.5
        w = float(params["w"])
        return {"mean": w, "per_task": {}}, {"replay": _replay(0.5 if w >= 4 else 0.1)}

    return train_grpo(_step, state, lambda i: jnp.float32(i), key=jax.random.key(0), rl=rl, workdir=workdir,
                      evaluate=evaluate, run_id=grpo_run_id(rl, seed=0, simulator="toy"),
                      progress=lambda point, eta: "", log=log)


def test_a_tripped_guard_rolls_the_policy_and_optimizer_back_and_a_resumed_run_does_the_same(tmp_path):
    lines = []
    result, points = _run(str(tmp_path / "a"), _rl(8, 0.2), log=lines.append)
    # w: 2 at step 2 (passes), 4 at step 4 (trips: back to 2), then 4 again at 6 and 8 (trip again)
    assert [(p["step"], p["mean"], p["guard"]["trip"]) for p in points] == [
        (0, 0.0, False), (2, 2.0, False), (4, 4.0, True), (6, 4.0, True), (8, 4.0, True)]
    assert all(p["guard"]["rolled_back_to"] == 2 for p in points if p["guard"]["trip"])
    assert float(result.state.params["w"]) == 2.0 and int(result.state.opt_state) == 2  # the step-2 state
    assert int(result.state.step) == 8  # the step counter goes on: later steps draw new keys
    assert any("exploitation guard tripped" in line and "rolled back to step 2" in line for line in lines)

    # killed after the step-4 checkpoint (which holds the rolled-back state), then resumed to step 8
    _run(str(tmp_path / "b"), _rl(4, 0.2))
    resumed, resumed_points = _run(str(tmp_path / "b"), _rl(8, 0.2))
    assert resumed.first_step == 4 and resumed_points == points
    np.testing.assert_array_equal(jax.device_get(resumed.state.params["w"]), jax.device_get(result.state.params["w"]))
    assert int(resumed.state.opt_state) == int(result.state.opt_state)
    with open(os.path.join(tmp_path / "b", "success_curve.json")) as f:
        assert json.load(f)["points"] == json.loads(json.dumps(points))


def test_without_a_margin_the_guard_is_off(tmp_path):
    result, points = _run(str(tmp_path), dataclasses.replace(_rl(6, 0.0)))
    assert float(result.state.params["w"]) == 6.0 and all("guard" not in p for p in points)
