"""Initial-state splits (train / eval / heldout are disjoint) and DART-style expert noise."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sim import expert, tasks
from sim.config import SimConfig
from sim.dataset import read_dataset
from sim.env import CpuEnv
from train import gen_data


@pytest.mark.parametrize("task_id", (0, 4, 9))
def test_demo_and_heldout_init_states_are_disjoint_from_evaluation_and_each_other(task_id):
    evaluation = tasks.split_init_states(task_id, "eval", tasks.NUM_INIT_STATES)
    np.testing.assert_array_equal(evaluation, tasks.fixed_init_states(task_id))  # unchanged
    train = tasks.split_init_states(task_id, "train", 300)
    heldout = tasks.split_init_states(task_id, "heldout", 60)
    assert not tasks.coinciding(train, evaluation).any()
    assert not tasks.coinciding(heldout, evaluation).any()
    assert not tasks.coinciding(heldout, train).any()
    # Deterministic, and a window of the stream is the same states.
    np.testing.assert_array_equal(tasks.split_init_states(task_id, "train", 5, start=10), train[10:15])
    # The check is real: a state coincides with itself and with a copy nudged below the tolerance.
    nudged = evaluation[:3].copy()
    nudged[:, -1] += tasks.SAME_STATE_TOL / 2
    assert tasks.coinciding(nudged, evaluation).all()
    with pytest.raises(ValueError, match="coincide"):
        tasks.assert_disjoint(np.concatenate([train[:4], nudged[:1]]), evaluation, "demos")


def test_split_stream_rejects_states_equal_to_evaluation_ones(monkeypatch):
    # Force the train stream to propose evaluation states first: they must be redrawn.
    evaluation = tasks.fixed_init_states(3)
    calls = {"n": 0}
    real = tasks.init_qpos

    def proposing_eval_first(task_id, draws, *, xp=np):
        calls["n"] += 1
        return evaluation[calls["n"] - 1] if calls["n"] <= 2 else real(task_id, draws, xp=xp)

    monkeypatch.setattr(tasks, "init_qpos", proposing_eval_first)
    tasks._split_stream.cache_clear()
    try:
        states = tasks.split_init_states(3, "train", 3, seed=7)
    finally:
        tasks._split_stream.cache_clear()
    assert calls["n"] >= 5 and not tasks.coinciding(states, evaluation).any()


def test_split_errors():
    with pytest.raises(ValueError, match="split"):
        tasks.split_init_states(0, "test", 1)
    with pytest.raises(ValueError, match="50"):
        tasks.split_init_states(0, "eval", 5, start=48)


def _replay_clean_labels(env, qpos, executed):
    """The expert's clean action at every state reached by executing ``executed``."""
    state = env.reset_to(qpos)
    est = expert.init(expert.privileged(env, state.data))
    labels = []
    for action in executed:
        _, clean, est = expert.act_labelled(expert.privileged(env, state.data), est, np.zeros(6))
        labels.append(clean)
        state = env.step(state, action)
    return np.stack(labels), state


def test_noisy_expert_records_the_clean_action_of_the_executed_state():
    env = CpuEnv(SimConfig(), 0)
    qpos = tasks.split_init_states(0, "train", 1)[0]
    out = expert.rollout_cpu(env, qpos, cfg=expert.ExpertConfig(noise=0.3), rng=np.random.default_rng(4),
                             max_steps=40, record=True)
    labels, executed = out["actions"], out["executed"]
    assert np.mean(np.any(np.abs(labels - executed) > 1e-6, axis=1)) > 0.5, "noise must change what is executed"
    replayed, last = _replay_clean_labels(env, qpos, executed)
    np.testing.assert_allclose(labels, replayed, atol=1e-9)
    np.testing.assert_allclose(last.data.qpos, out["states"][-1].data.qpos, atol=1e-9)
    # The label is not the executed action re-labelled: the noisy action differs from the label.
    assert not np.allclose(labels, executed)


def test_jax_policy_returns_noisy_executed_and_clean_label():
    env = CpuEnv(SimConfig(), 5)
    state = env.reset_to(env.init_states[2])
    priv = expert.privileged(env, state.data)
    _, clean_np, _ = expert.act_labelled(priv, expert.init(priv), np.zeros(6))
    priv_j = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), priv)
    est_j = jax.tree.map(jnp.asarray, expert.init(priv_j, xp=jnp))
    noise = jax.random.normal(jax.random.key(1), (6,), jnp.float32)
    executed, clean, _ = jax.jit(lambda p, e, n: expert.act_labelled(p, e, n, expert.ExpertConfig(noise=0.5), xp=jnp))(
        priv_j, est_j, noise)
    np.testing.assert_allclose(np.asarray(clean), clean_np, atol=1e-4)
    assert not np.allclose(np.asarray(executed), np.asarray(clean))


def test_gen_data_uses_train_split_and_records_it(tmp_path):
    out = str(tmp_path / "demos.hdf5")
    gen_data.main(["--task", "1", "--episodes", "2", "--out", out, "--resolution", "16", "--max-steps", "5",
                   "--renderer", "jax", "--noise", "0.3", "--no-wrist", "--init-start", "3"])
    info, episodes = read_dataset(out)
    assert info.env_args["env_kwargs"]["init_split"] == "train"
    env = CpuEnv(SimConfig(), 1)
    expected = tasks.split_init_states(1, "train", 2, start=3)
    for i, ep in enumerate(episodes):
        assert ep.init_split == "train" and ep.init_state_id == 3 + i
        start = env.reset_to(expected[i])
        np.testing.assert_allclose(ep.init_state[1:1 + env.nq], start.data.qpos, atol=1e-6)
        # Labels are the clean actions of the states the executed (noisy) actions led to.
        replayed, _ = _replay_clean_labels(env, expected[i], ep.executed_actions)
        np.testing.assert_allclose(ep.actions, replayed, atol=1e-6)
        assert not np.allclose(ep.actions, ep.executed_actions)
    settled_eval = np.stack([env.reset_to(q).data.qpos for q in env.init_states])
    assert not tasks.coinciding(np.stack([ep.init_state[1:1 + env.nq] for ep in episodes]), settled_eval).any()
