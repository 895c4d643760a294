"""Tiny RL configs, demonstrations and episodes for the policy, reward-model and entry-point tests."""

from __future__ import annotations

import numpy as np

from sword_jax.rl import data as rl_data
from sword_jax.rl.config import PolicyConfig, RewardModelConfig, RLConfig, SFTConfig

# Command-line overrides that make the RL entry points' models tiny.
TINY_RL = ["--rl.image_size=8", "--rl.policy.width=16", "--rl.policy.heads=2", "--rl.policy.layers=1",
           "--rl.action_bins=8", "--rl.reward_model.width=4", "--rl.policy.max_instruction_bytes=48"]

POLICY_CFG = RLConfig(image_size=8, action_bins=16, proprio_dim=4,
               policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=48, proprio_encoding="raw"),
               sft=SFTConfig(learning_rate=3e-3), reward_model=RewardModelConfig(width=4, learning_rate=3e-3))
# LIBERO-Spatial instructions differ in a few words only
TEXTS = ["pick up the black bowl on the plate and place it on the plate",
         "pick up the black bowl on the stove and place it on the plate"]


def write_demos(path, solved_steps=4, *, steps=12, size=16):
    """Four ``steps``-step demonstrations (``size`` x ``size`` frames) in a dataset file; even ones are solved at
    the end."""
    from sim.dataset import DatasetInfo, Episode, write_dataset

    rng = np.random.default_rng(0)
    episodes = []
    for i in range(4):
        t = steps
        succeeds = (np.arange(t) >= t - solved_steps) & (i % 2 == 0)  # even episodes are solved over their last 4 actions
        episodes.append(Episode(
            actions=rng.uniform(-1, 1, (t, 7)).astype(np.float32), states=np.zeros((t, 3), np.float32),
            rewards=succeeds.astype(np.float32), dones=succeeds.astype(np.uint8),
            agentview_rgb=rng.integers(0, 255, (t, size, size, 3), dtype=np.uint8),
            ee_states=np.zeros((t, 6), np.float32), gripper_states=np.zeros((t, 2), np.float32),
            joint_states=np.zeros((t, 7), np.float32), task_id=i % 2,
            language_instruction=["pick up the bowl on the plate", "pick up the bowl on the stove"][i % 2]))
    write_dataset(path, episodes, DatasetInfo(env_name="test"))
    return path


def brightening_episodes(texts=tuple(TEXTS * 2)):
    """Four 12-step episodes whose frames brighten over time (failures stay dark); the first two succeed."""
    e, t = 4, 12
    level = np.linspace(0, 255, t).astype(np.uint8)
    frames = np.broadcast_to(level[None, :, None, None, None], (e, t, 8, 8, 3)).copy()
    frames[2:] //= 3  # failures never get bright
    return rl_data.EpisodeSet(frames, np.zeros((e, t, 7), np.float32), np.zeros((e, t, 4), np.float32),
                              np.full(e, t), np.array([True, True, False, False]), tuple(texts))


def reward_batches(cfg, poison_at=None):
    """``batch_at(step)``: class-balanced batches of brightening frames; step ``poison_at``'s holds a NaN frame."""
    episodes = brightening_episodes(("a", "b", "a", "b"))
    labels = rl_data.success_labels(episodes, positive_tail=3)

    def batch_at(step):
        batch = rl_data.sample_reward_batch(episodes, labels, 8, np.random.default_rng(step))
        if step == poison_at:
            batch = dict(batch, frames=np.asarray(batch["frames"], np.float32) / 255.0)
            batch["frames"][0, 0, 0, 0] = np.nan
        return batch

    return batch_at
