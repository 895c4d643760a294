"""The supervised policy's own rollouts as world-model data (sim/policy_rollouts.py)."""

import dataclasses
import functools
import multiprocessing
import os

import h5py
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
    summary = policy_rollouts.write_policy_episodes(gen.out, functools.partial(make_act_fns, graphdef, rl), params, rl,
                                                    gen, key=jax.random.key(1))
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
        policy_rollouts.write_policy_episodes(gen.out, functools.partial(make_act_fns, graphdef, rl), params, rl, gen,
                                              key=jax.random.key(1))


def _reference_policy_episodes(act, params, rl, gen, *, key, batch):
    """The recording as first written: pure steps keeping every state, the batch rendered at each decision for
    the policy, and each episode's frames rendered again, all of them, when it is written."""
    import sim
    from sim import tasks
    from sword_jax.rl.policy import tokenize_instructions

    starts = [(task, i, qpos) for task in gen.tasks for i, qpos in enumerate(datagen.init_states(gen, task))]
    envs = {task: sim.load("libero_spatial", task_id=task, backend="cpu", resolution=gen.resolution,
                           max_steps=gen.max_steps) for task in gen.tasks}
    frames = datagen.JaxFrames(datagen.render_scene(envs[gen.tasks[0]]), gen.resolution)
    k, out = rl.env.execute_steps, []
    for b, begin in enumerate(range(0, len(starts), batch)):
        group = starts[begin:begin + batch]
        states = [[envs[task].reset_to(qpos)] for task, _, qpos in group]
        actions = [[] for _ in group]
        text = jax.numpy.asarray(tokenize_instructions([tasks.LANGUAGE[t] for t, _, _ in group],
                                                       rl.policy.max_instruction_bytes))
        for c in range(-(-gen.max_steps // k)):
            now = [s[-1] for s in states]
            rgb = frames([s.data for s in now], "agentview")["rgb"]
            proprio = np.stack([np.asarray(s.obs["proprio"], np.float32) for s in now])[:, : rl.proprio_dim]
            chunk = act(params, jax.numpy.asarray(rgb), text, jax.numpy.asarray(proprio),
                        jax.random.fold_in(jax.random.fold_in(key, b), c), False)[3]
            chunk = np.clip(np.asarray(chunk, np.float64), -1.0, 1.0)
            for i, (task, _, _) in enumerate(group):
                for j in range(min(k, gen.max_steps - len(actions[i]))):
                    states[i].append(envs[task].step(states[i][-1], chunk[i, j]))
                    actions[i].append(chunk[i, j])
        for i, (task, index, _) in enumerate(group):
            seen = [s.data for s in states[i][:-1]]
            out.append({"task": task, "index": index, "actions": np.stack(actions[i]),
                        "after": np.asarray([float(s.done) for s in states[i][1:]]),
                        "states": np.stack([datagen.flat_state(d) for d in seen]),
                        "proprio": np.stack([np.asarray(s.obs["proprio"]) for s in states[i][:-1]]),
                        "joints": np.stack([np.asarray(d.qpos[:7]) for d in seen]),
                        **{f"agentview_{n}": v for n, v in frames(seen, "agentview").items()}})
    return out


def test_policy_rollouts_record_what_rendering_every_decision_and_episode_again_recorded(tmp_path):
    """Each step's frames rendered once for the whole batch and stepping in place record the same episodes,
    bit for bit, as rendering the batch at each decision and every episode's frames again at the end with pure
    steps: the same actions, states, success flags and frames (two batches, the second a partial one; a last
    chunk cut short)."""
    cfg = sword.get("tiny")
    rl = dataclasses.replace(cfg.rl, env=dataclasses.replace(cfg.rl.env, execute_steps=3, action_ensemble=False))
    graphdef, params = build_policy(rl, seed=0)
    act = make_act_fns(graphdef, rl)
    gen = datagen.GenDataConfig(out=str(tmp_path / "rollouts.hdf5"), tasks=(0, 3, 5), episodes=1, backend="cpu",
                                resolution=16, max_steps=8, stop_at_success=False, wrist_camera=False,
                                overwrite=False, renderer="jax", init_split="train", init_start=1,
                                init_seed=cfg.sim.init_seed)
    key = jax.random.key(5)
    recorded = list(policy_rollouts.record_policy_episodes(act, params, rl, gen, key=key, batch=2))
    reference = _reference_policy_episodes(act, params, rl, gen, key=key, batch=2)
    assert len(recorded) == len(reference) == 3
    for (episode, success), ref in zip(recorded, reference):
        assert (episode.task_id, episode.init_state_id) == (ref["task"], gen.init_start + ref["index"])
        assert success == bool(ref["after"].max() > 0)
        np.testing.assert_array_equal(episode.actions, ref["actions"])
        np.testing.assert_array_equal(episode.executed_actions, ref["actions"])
        np.testing.assert_array_equal(episode.rewards, ref["after"])
        np.testing.assert_array_equal(episode.states, ref["states"])
        np.testing.assert_array_equal(episode.ee_states, ref["proprio"][:, :6])
        np.testing.assert_array_equal(episode.gripper_states, ref["proprio"][:, 6:8])
        np.testing.assert_array_equal(episode.joint_states, ref["joints"])
        for name in ("agentview_rgb", "agentview_depth", "agentview_seg"):
            np.testing.assert_array_equal(getattr(episode, name), ref[name], err_msg=name)
            assert getattr(episode, name).dtype == ref[name].dtype
    # the episodes differ from one another, so equal lists are not a coincidence of still arms
    assert len({e.actions.tobytes() for e, _ in recorded}) == 3 and recorded[0][0].agentview_rgb.std() > 0


def _tiny_policy(tmp_path, tasks):
    cfg = sword.get("tiny")
    rl = dataclasses.replace(cfg.rl, env=dataclasses.replace(cfg.rl.env, execute_steps=3, action_ensemble=False))
    graphdef, params = build_policy(rl, seed=0)
    gen = datagen.GenDataConfig(out=str(tmp_path / "rollouts.hdf5"), tasks=tasks, episodes=1, backend="cpu",
                                resolution=16, max_steps=6, stop_at_success=False, wrist_camera=False,
                                overwrite=False, renderer="jax", init_split="train", init_start=0,
                                init_seed=cfg.sim.init_seed)
    return rl, graphdef, params, gen


def _act_in_a_worker_allocating_as_used(graphdef, rl):
    """``make_act_fns``, checking that a worker process does not preallocate the accelerator."""
    if multiprocessing.parent_process() is not None:
        assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    return make_act_fns(graphdef, rl)


def _act_refusing_one_episode_batches(graphdef, rl):
    act = make_act_fns(graphdef, rl)

    def refusing(params, frames, *args):
        if frames.shape[0] == 1:
            raise ValueError("a one-episode batch")
        return act(params, frames, *args)

    return refusing


def _file_contents(path):
    """Every group's and dataset's attributes and every dataset's dtype, shape, filter and bytes, by name."""
    contents = {}

    def attrs(obj):
        return {k: np.asarray(v).tobytes() if isinstance(v, np.ndarray) else v for k, v in obj.attrs.items()}

    def visit(name, obj):
        contents[name] = attrs(obj)
        if isinstance(obj, h5py.Dataset):
            contents[name + ":data"] = (obj.dtype.str, obj.shape, obj.compression, obj[()].tobytes())

    with h5py.File(path, "r") as f:
        contents["/"] = attrs(f)
        f.visititems(visit)
    return contents


def test_worker_processes_write_the_file_of_one_process(tmp_path):
    """Two processes recording alternate batches (three of them, the last a partial one) write the same file as
    one process: every dataset and attribute bit for bit, the episodes in the same order; the same summary."""
    rl, graphdef, params, gen = _tiny_policy(tmp_path, tasks=(0, 3, 5, 7, 9))
    make_act = functools.partial(_act_in_a_worker_allocating_as_used, graphdef, rl)
    paths, summaries = {}, {}
    for workers in (1, 2):
        paths[workers] = str(tmp_path / f"workers{workers}.hdf5")
        summaries[workers] = policy_rollouts.write_policy_episodes(
            paths[workers], make_act, params, rl, dataclasses.replace(gen, out=paths[workers]),
            key=jax.random.key(3), batch=2, workers=workers)
    assert {k: v for k, v in summaries[2].items() if k != "path"} == {
        k: v for k, v in summaries[1].items() if k != "path"}
    assert summaries[1]["episodes"] == 5
    one, two = _file_contents(paths[1]), _file_contents(paths[2])
    assert list(one) == list(two)
    for name in one:
        assert one[name] == two[name], name
    _, episodes = read_dataset(paths[2])
    assert [e.task_id for e in episodes] == [0, 3, 5, 7, 9]
    assert len({e.actions.tobytes() for e in episodes}) == 5  # distinct episodes: the order is checked
    assert sorted(os.listdir(tmp_path)) == ["workers1.hdf5", "workers2.hdf5"]  # no temporary files left


def test_a_failing_worker_fails_the_recording_naming_it_and_leaves_no_files(tmp_path):
    rl, graphdef, params, gen = _tiny_policy(tmp_path, tasks=(0, 3, 5))
    with pytest.raises(RuntimeError, match=r"(?s)policy_data worker 1 of 2 .*a one-episode batch"):
        policy_rollouts.write_policy_episodes(gen.out, functools.partial(_act_refusing_one_episode_batches, graphdef, rl),
                                              params, rl, gen, key=jax.random.key(3), batch=2, workers=2)
    assert os.listdir(tmp_path) == []
    with pytest.raises(ValueError, match="workers must be >= 1"):
        policy_rollouts.write_policy_episodes(gen.out, functools.partial(make_act_fns, graphdef, rl), params, rl, gen,
                                              key=jax.random.key(3), workers=0)
