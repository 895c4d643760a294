"""The guards of GRPO in a learned simulator (sword_jax.rl.sim_guard: false success of the replay, real success of
the refreshes) and their rollback in the GRPO loop: judged verdicts, the rollback restoring the last passing
policy and optimizer state, exact resume."""

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import grpo
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, RefreshConfig, RLConfig
from sword_jax.rl.grpo_loop import grpo_run_id, train_grpo
from sword_jax.rl.sim_guard import FalseSuccessGuard, RealSuccessGuard


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


def _refresh(real_success: float, episodes: int = 64) -> dict:
    return {"step": 0, "real_episodes": episodes, "real_episodes_used": episodes, "real_success": real_success}


def test_real_success_guard_sets_its_baseline_from_the_first_judged_refresh_and_trips_only_past_the_margin():
    guard = RealSuccessGuard(0.15, min_episodes=32)
    assert not guard.observe(None).trip and guard.baseline is None  # an evaluation without a refresh
    assert guard.observe({}).reason == "no refresh: not judged"
    skipped = guard.observe({"step": 0, "skipped": "the budget of 64 real episodes is spent", "real_episodes": 0})
    assert not skipped.trip and guard.baseline is None and "skipped" in skipped.reason
    few = guard.observe(_refresh(0.0, episodes=31))
    assert not few.trip and guard.baseline is None and "31 real episodes (< 32): not judged" == few.reason
    missing = guard.observe({"real_episodes": 64})
    assert not missing.trip and guard.baseline is None and "no real success" in missing.reason
    first = guard.observe(_refresh(39 / 64))  # the seed measured on 4 GPUs: 0.609 at step 0
    assert not first.trip and guard.baseline == pytest.approx(0.609375)
    assert not guard.observe(_refresh(30 / 64)).trip  # 0.469: 0.141 below, within the margin
    assert not guard.observe(_refresh(1.0)).trip and guard.baseline == pytest.approx(0.609375)  # baseline kept
    tripped = guard.observe(_refresh(19 / 64))  # 0.297: 0.312 below
    assert tripped.trip and tripped.rate == pytest.approx(0.296875) and tripped.baseline == pytest.approx(0.609375)
    assert "real success 0.297 < baseline 0.609 - margin 0.150 (64 real episodes)" == tripped.reason
    assert not guard.observe(_refresh(0.0, episodes=16)).trip  # too few episodes to judge
    assert not guard.observe({"skipped": "budget spent", "real_episodes": 0, "real_success": 0.0}).trip
    for bad in ({"margin": 0.0}, {"margin": 1.0}, {"margin": -0.1}, {"margin": 0.1, "min_episodes": 0}):
        with pytest.raises(ValueError, match="RealSuccessGuard"):
            RealSuccessGuard(**bad)


@pytest.mark.parametrize("bad, message", [
    (dict(every=2, episodes=64, budget=128, real_guard_margin=1.0), r"real_guard_margin must be in \[0, 1\)"),
    (dict(every=2, episodes=64, budget=128, real_guard_margin=-0.1), r"real_guard_margin must be in \[0, 1\)"),
    (dict(every=2, episodes=64, budget=128, real_guard_min_episodes=0), "real_guard_min_episodes >= 1"),
    (dict(every=0, real_guard_margin=0.2), r"needs rl.refresh.every > 0"),
    (dict(every=2, episodes=16, budget=128, real_guard_margin=0.2), "would judge no refresh")])
def test_refresh_config_refuses_bad_real_guard_settings(bad, message):
    with pytest.raises(ValueError, match=message):
        RLConfig(refresh=RefreshConfig(**bad)).validate()


def test_refresh_config_takes_the_real_guard_settings_and_run_ids_name_them_only_when_on():
    on = RLConfig(refresh=RefreshConfig(every=2, episodes=64, budget=128, real_guard_margin=0.15,
                                        real_guard_min_episodes=48))
    on.validate()
    RLConfig(refresh=RefreshConfig(every=2, episodes=16, budget=128, real_guard_min_episodes=48)).validate()  # off
    assert RefreshConfig().real_guard_margin == 0.0 and RefreshConfig().real_guard_min_episodes == 32
    run_id = grpo_run_id(on, seed=0, simulator="world_model_refreshed")
    assert run_id["rl.refresh.real_guard_margin"] == 0.15 and run_id["rl.refresh.real_guard_min_episodes"] == 48
    # off: a run from before the guard existed has the same identity, so it still resumes
    assert not any("real_guard" in k for k in grpo_run_id(RLConfig(), seed=0, simulator="world_model_refreshed"))


def _rl(steps: int, margin: float, real_margin: float = 0.0) -> RLConfig:
    return RLConfig(grpo=GRPOConfig(steps=steps, eval_every=2), imagined=ImaginedConfig(guard_margin=margin),
                    refresh=RefreshConfig(every=2, episodes=64, budget=1024, real_guard_margin=real_margin))


@jax.jit
def _step(state, batch, key):
    """Adds 1 to the parameter and counts the steps in a stand-in optimizer state."""
    params = {"w": state.params["w"] + 1.0}
    return state.replace(params=params, opt_state=state.opt_state + 1, step=state.step + 1), {"loss": params["w"]}


def _exploited(w: float) -> dict:
    """The simulator is exploited once w reaches 4: false success 0.1 -> 0.5."""
    return {"replay": _replay(0.5 if w >= 4 else 0.1)}


def _run(workdir, rl, log=lambda line: None, extra=_exploited):
    state = grpo.init_state({"w": jnp.zeros((), jnp.float32)}, rl)
    state = state.replace(opt_state=jnp.zeros((), jnp.int32))

    def evaluate(done, params):
        w = float(params["w"])
        return {"mean": w, "per_task": {}}, extra(w)

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


def _verified_exploitation(w: float) -> dict:
    """The replay of real episodes stays clean (0.1) while the policy's own imagined groups, executed for real,
    show the exploitation once w reaches 4: false success 0.1 -> 0.5."""
    return {"replay": _replay(0.1), "verify": _replay(0.5 if w >= 4 else 0.1)}


def test_the_guard_on_verify_reads_the_check_of_imagined_rollouts_and_resumes_the_same(tmp_path):
    rl = _rl(8, 0.2)
    rl = dataclasses.replace(rl, imagined=dataclasses.replace(rl.imagined, guard_on="verify"),
                             refresh=dataclasses.replace(rl.refresh, verify_starts=8))
    rl.validate()
    result, points = _run(str(tmp_path / "a"), rl, extra=_verified_exploitation)
    assert [(p["step"], p["guard"]["trip"]) for p in points] == [(0, False), (2, False), (4, True), (6, True),
                                                                  (8, True)]
    assert float(result.state.params["w"]) == 2.0
    _run(str(tmp_path / "b"), dataclasses.replace(rl, grpo=dataclasses.replace(rl.grpo, steps=4)),
         extra=_verified_exploitation)
    resumed, resumed_points = _run(str(tmp_path / "b"), rl, extra=_verified_exploitation)
    assert resumed.first_step == 4 and resumed_points == points
    # the replay alone would not have tripped
    _, clean = _run(str(tmp_path / "c"), _rl(8, 0.2), extra=_verified_exploitation)
    assert not any(p["guard"]["trip"] for p in clean)
    assert grpo_run_id(rl, seed=0, simulator="toy")["rl.imagined.guard_on"] == "verify"
    assert "rl.imagined.guard_on" not in grpo_run_id(_rl(8, 0.2), seed=0, simulator="toy")


@pytest.mark.parametrize("bad, message", [
    (dict(imagined=ImaginedConfig(guard_on="detector")), "guard_on must be replay|verify"),
    (dict(imagined=ImaginedConfig(guard_on="verify"), refresh=RefreshConfig(every=2, episodes=64, budget=128)),
     "needs rl.refresh.every > 0 and rl.refresh.verify_starts > 0")])
def test_the_guard_on_verify_needs_the_check(bad, message):
    with pytest.raises(ValueError, match=message):
        RLConfig(**bad).validate()


def _real_decline(w: float) -> dict:
    """The replay's false success stays at 0.6 (step 0's, so the exploitation guard cannot trip) while the
    refreshes' real success falls once w reaches 4: 0.61 -> 0.30; the step-0 refresh holds too few episodes
    to judge, so step 2's sets the baseline."""
    real_success = 0.296875 if w >= 4 else 0.609375
    return {"replay": _replay(0.6), "refresh": _refresh(real_success, episodes=16 if w == 0 else 64)}


def test_a_tripped_real_success_guard_rolls_the_policy_back_and_a_resumed_run_does_the_same(tmp_path):
    lines = []
    rl = _rl(8, 0.1, real_margin=0.15)
    result, points = _run(str(tmp_path / "a"), rl, log=lines.append, extra=_real_decline)
    # w: 2 at step 2 (sets the baseline), 4 at step 4 (trips: back to 2), then 4 again at 6 and 8 (trip again)
    assert [(p["step"], p["mean"], p["guard"]["trip"], p["guard"]["real_success"]["trip"]) for p in points] == [
        (0, 0.0, False, False), (2, 2.0, False, False), (4, 4.0, False, True), (6, 4.0, False, True),
        (8, 4.0, False, True)]
    assert [p["guard"]["real_success"]["baseline"] for p in points] == [None] + [0.609375] * 4
    assert points[4]["guard"]["real_success"]["rate"] == 0.296875 and points[4]["guard"]["false_success"] == 0.6
    assert [p["guard"].get("rolled_back_to") for p in points] == [None, None, 2, 2, 2]
    assert float(result.state.params["w"]) == 2.0 and int(result.state.opt_state) == 2  # the step-2 state
    assert int(result.state.step) == 8
    tripped = [line for line in lines if "tripped" in line]
    assert len(tripped) == 3 and tripped[0] == ("GRPO step 4: real-success guard tripped (real success 0.297 < "
                                                "baseline 0.609 - margin 0.150 (64 real episodes)); policy rolled "
                                                "back to step 2")

    # killed after the step-4 checkpoint (which holds the rolled-back state), then resumed to step 8: the
    # baseline comes back from step 2's point (step 0's refresh was not judged)
    _run(str(tmp_path / "b"), _rl(4, 0.1, real_margin=0.15), extra=_real_decline)
    resumed, resumed_points = _run(str(tmp_path / "b"), rl, extra=_real_decline)
    assert resumed.first_step == 4 and resumed_points == points
    np.testing.assert_array_equal(jax.device_get(resumed.state.params["w"]), jax.device_get(result.state.params["w"]))
    assert int(resumed.state.opt_state) == int(result.state.opt_state)


def test_the_real_success_guard_alone_rolls_back_and_either_guard_tripping_rolls_back_once(tmp_path):
    lines = []
    result, points = _run(str(tmp_path / "a"), _rl(6, 0.0, real_margin=0.15), log=lines.append, extra=_real_decline)
    assert [sorted(p["guard"]) for p in points] == [["real_success"]] * 2 + [["real_success", "rolled_back_to"]] * 2
    assert float(result.state.params["w"]) == 2.0

    def both(w):  # both guards trip from w = 4 on
        return {"replay": _replay(0.5 if w >= 4 else 0.1), "refresh": _refresh(0.2 if w >= 4 else 0.6)}

    lines.clear()
    result, points = _run(str(tmp_path / "b"), _rl(6, 0.2, real_margin=0.15), log=lines.append, extra=both)
    assert [(p["guard"]["trip"], p["guard"]["real_success"]["trip"]) for p in points] == [
        (False, False), (False, False), (True, True), (True, True)]
    assert float(result.state.params["w"]) == 2.0 and int(result.state.opt_state) == 2
    assert sum("exploitation guard tripped" in line for line in lines) == 2
    assert sum("real-success guard tripped" in line for line in lines) == 2
