"""The supervised policy's own rollouts as world-model data (sim/policy_rollouts.py)."""

import dataclasses

import jax
import numpy as np
import pytest

from configs import sword
from sim import datagen, policy_rollouts
from sim.dataset import read_dataset
from sword_jax.rl.env_rollout import make_act_fns
from sword_jax.rl.policy import build_policy


def test_policy_rollouts_are_fixed_length_replayable_episodes(tmp_path):
    """Every episode has exactly max_steps executed actions from its training initial state (even after a
    success), frames with depth and segmentation, and replaying its actions in the C engine reproduces
    its recorded states and success flags."""
    import sim

    cfg = sword.get("tiny")
    rl = dataclasses.replace(cfg.rl, env=dataclasses.replace(cfg.rl.env, execute_steps=4, action_ensemble=False))
    graphdef, params = build_policy(rl, seed=0)
    gen = datagen.GenDataConfig(out=str(tmp_path / "rollouts.hdf5"), tasks=(0, 3), episodes=1, backend="cpu",
                                resolution=16, max_steps=10, stop_at_success=False, wrist_camera=False,
                                overwrite=False, renderer="jax", init_split="train", init_start=0,
                                init_seed=cfg.sim.init_seed)
    summary = policy_rollouts.write_policy_episodes(gen.out, make_act_fns(graphdef, rl), params, rl, gen,
                                                    key=jax.random.key(1))
    assert summary["episodes"] == 2
    info, episodes = read_dataset(gen.out)
    assert [e.task_id for e in episodes] == [0, 3] and info.seg_class_names[0] == "background"
    for episode in episodes:
        assert episode.num_samples == 10 and episode.init_split == "train"
        assert episode.agentview_rgb.shape == (10, 16, 16, 3) and episode.agentview_depth.shape == (10, 16, 16)
        assert episode.agentview_seg.shape == (10, 16, 16)
        np.testing.assert_array_equal(episode.actions, episode.executed_actions)
        assert np.abs(episode.actions).max() <= 1.0 and np.unique(episode.actions, axis=0).shape[0] > 1
        env = sim.load("libero_spatial", task_id=episode.task_id, backend="cpu", resolution=16, max_steps=10)
        qpos = datagen.init_states(gen, episode.task_id)[0]
        state = env.reset_to(qpos)
        replayed, done = [datagen.flat_state(state.data)], []
        for action in episode.actions:
            state = env.step(state, action)
            replayed.append(datagen.flat_state(state.data))
            done.append(float(state.done))
        np.testing.assert_allclose(np.stack(replayed[:-1]), episode.states, atol=1e-9)
        np.testing.assert_array_equal(np.asarray(done), episode.rewards)
    with pytest.raises(FileExistsError):  # nothing already written is replaced without overwrite
        policy_rollouts.write_policy_episodes(gen.out, make_act_fns(graphdef, rl), params, rl, gen, key=jax.random.key(1))
