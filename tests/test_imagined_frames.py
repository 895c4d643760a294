"""sword_jax.rl.imagined_frames: episodes replayed window by window through a designed simulator whose frames are
known in closed form (the start frame brightened by the running sum of action dim 0), so every imagined frame's
value, its place in the episode and the real frames kept at window starts can be checked exactly."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.rl import data as rl_data
from sword_jax.rl.imagined_frames import imagined_episode_frames, window_starts
from sword_jax.rl.learned_simulator import LearnedSimulator

SIZE, GAIN = 8, 0.01


def _simulator(execute_len=4, chunk_len=8, starts=None):
    """State: the frame (from the start) and the start's context marker; each executed action adds
    GAIN * action[0] to every pixel. ``starts`` collects the context each start was encoded with."""

    def init_fn(params, start):
        del params
        latents, _ = start.latents
        return (start.frame, latents)

    def step_fn(params, state, chunk, key):
        del params, key
        frame, latents = state
        steps = GAIN * jnp.cumsum(chunk[:execute_len, 0])
        frames = jnp.clip(frame[None] + steps[:, None, None, None], 0.0, 1.0)
        return (frames[-1], latents), frames

    def observe_fn(params, state):
        del params, state
        return jnp.zeros((2,), jnp.float32), jnp.float32(1.0)

    return LearnedSimulator(params={}, init_fn=init_fn, step_fn=step_fn, observe_fn=observe_fn, chunk_len=chunk_len,
                            frame_size=SIZE, execute_len=execute_len, action_dim=7)


def _episodes(lengths, t=24):
    rng = np.random.default_rng(0)
    e = len(lengths)
    frames = rng.integers(40, 120, size=(e, t, SIZE, SIZE, 3)).astype(np.uint8)
    actions = np.zeros((e, t, 7), np.float32)
    actions[..., 0] = rng.integers(0, 3, size=(e, t))  # brightness steps of 0, 1 or 2 x GAIN
    return rl_data.EpisodeSet(frames=frames, actions=actions, proprio=np.zeros((e, t, 2), np.float32),
                              lengths=np.asarray(lengths, np.int64), success=np.ones(e, bool),
                              instructions=tuple(f"task {i}" for i in range(e)))


def _encode(first, history):
    assert first.ndim == 4 and history.ndim == 5  # [n, H, W, 3] and [n, 4 (k + 1), H, W, 3], in [0, 1]
    assert float(jnp.max(history)) <= 1.0
    return jnp.mean(history, axis=(1, 2, 3, 4))


def test_window_starts():
    episode, t0 = window_starts(np.array([10, 1, 13, 2, 7]), 5)
    # each window: its real start and the 5 frames its replay shows. Frames 0..9: windows at 0 (shows 1..5) and
    # 6 (shows 7..9); one frame: none; 0..12: 0 and 6 (shows up to 11), then 12, the last frame, starts nothing
    assert episode.tolist() == [0, 0, 2, 2, 3, 4] and t0.tolist() == [0, 6, 0, 6, 0, 0]
    with pytest.raises(ValueError, match="window must be >= 1"):
        window_starts(np.array([3]), 0)


@pytest.mark.parametrize("batch", [1, 3, 64])
def test_each_window_replays_its_actions_from_the_real_frame(batch):
    episodes = _episodes([17, 9, 1, 12])
    window = 6
    out = imagined_episode_frames(_simulator(), _encode, episodes, window=window, key=jax.random.key(0),
                                  batch=batch)
    assert out.shape == episodes.frames.shape and out.dtype == np.uint8
    for e, length in enumerate(episodes.lengths):
        real = episodes.frames[e]
        for t in range(length):
            s = (t // (window + 1)) * (window + 1)  # the window's start: its real frame
            if t == s:
                expected = real[t]
            else:  # the real start frame plus the actions s .. t - 1 replayed
                bright = GAIN * episodes.actions[e, s:t, 0].sum()
                expected = np.clip(np.round((real[s] / 255.0 + bright) * 255.0), 0, 255)
            np.testing.assert_allclose(out[e, t], expected, atol=1, err_msg=f"episode {e}, frame {t}")
        assert (out[e, length:] == out[e, length - 1]).all()  # the padding repeats the last frame
    assert (out[2] == episodes.frames[2, 0]).all()  # an episode of one frame has no window: real, padded
    # a window that ends inside the episode leaves the next window's start real
    assert (out[0, 7] == episodes.frames[0, 7]).all() and (out[0, 14] == episodes.frames[0, 14]).all()
    assert not (out[0, 6] == episodes.frames[0, 6]).all()


def test_the_batch_does_not_change_the_frames_and_bad_inputs_are_refused():
    episodes = _episodes([17, 9, 12])
    runs = [imagined_episode_frames(_simulator(), _encode, episodes, window=8, key=jax.random.key(1), batch=b)
            for b in (2, 5)]
    np.testing.assert_array_equal(runs[0], runs[1])  # a deterministic simulator: the batching is invisible
    with pytest.raises(ValueError, match="simulator shows 16 x 16"):
        imagined_episode_frames(_simulator().replace(frame_size=16), _encode, episodes, window=8,
                                key=jax.random.key(0))
    with pytest.raises(ValueError, match=r"frames must be \[E, T, H, W, 3\] uint8"):
        bad = rl_data.EpisodeSet(episodes.frames.astype(np.float32), episodes.actions, episodes.proprio,
                                 episodes.lengths, episodes.success, episodes.instructions)
        imagined_episode_frames(_simulator(), _encode, bad, window=8, key=jax.random.key(0))
    with pytest.raises(ValueError, match="batch must be >= 1"):
        imagined_episode_frames(_simulator(), _encode, episodes, window=8, key=jax.random.key(0), batch=0)


def test_with_the_prefix_each_window_starts_from_the_whole_episodes_latents():
    """rl.imagined.start_encoding=prefix: every window's start latents are encoded from its episode's frame 0 on
    (``encode`` is never called), so at a keyframe past the first context latent they are the whole episode's; the
    frames the replays show are the window run's. With the window they are encode_history's, as before."""
    from sword_jax.rl.world_model_sim import encode_history
    from tests.support.vae import encoders, relative_error, tiny_vae, whole_latents

    cfg, vae_graphdef, vae_state = tiny_vae()
    size, t = cfg.data.image_size, 25
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 256, (2, t, size, size, 3), dtype=np.uint8)
    episodes = rl_data.EpisodeSet(frames=frames, actions=np.zeros((2, t, 7), np.float32),
                                  proprio=np.zeros((2, t, 2), np.float32), lengths=np.array([25, 18]),
                                  success=np.ones(2, bool), instructions=("a", "b"))
    sim = _simulator().replace(frame_size=size)
    encode, encode_prefix = encoders()
    seen = {"prefix": [], "window": []}

    def recorded(name, fn):
        def encode_and_keep(*args):
            latents = fn(*args)
            seen[name].append(np.asarray(latents))
            return latents
        return encode_and_keep

    def refused(first, history):
        raise AssertionError("the window encoder was called with start_encoding=prefix")

    window = 7  # windows start at frames 0, 8, 16 (and 24 is the first episode's last frame)
    out = imagined_episode_frames(sim, refused, episodes, window=window, key=jax.random.key(0), batch=2,
                                  encode_prefix=recorded("prefix", encode_prefix))
    same = imagined_episode_frames(sim, recorded("window", encode), episodes, window=window, key=jax.random.key(0),
                                   batch=2)
    np.testing.assert_array_equal(out, same)
    ep, t0 = window_starts(episodes.lengths, window)
    assert t0.tolist() == [0, 8, 16, 0, 8, 16]
    got = np.concatenate(seen["prefix"])[: len(ep)]  # batches of 2 windows, in order
    whole = whole_latents(frames[:, :t])  # (2, 1 + 6, ...)
    later = t0 >= 4  # at frame 0 the keyframe is held still (keyframe_window's prefix), not the episode's own
    truth = np.stack([whole[ep, 0], whole[ep, t0 // 4]], axis=1)
    assert relative_error(got[later], truth[later]) < 1e-4
    unit = jnp.asarray(frames, jnp.float32) / jnp.float32(255.0)
    hist = np.maximum(t0[:, None] - 7 + np.arange(8)[None], 0)
    before = np.concatenate([encode_history(vae_graphdef, vae_state, unit[ep[lo:lo + 2], 0],  # in its batches
                                            unit[ep[lo:lo + 2, None], hist[lo:lo + 2]]) for lo in range(0, len(ep), 2)])
    np.testing.assert_array_equal(np.concatenate(seen["window"])[: len(ep)], np.asarray(before))
    assert relative_error(np.concatenate(seen["window"])[: len(ep)][later], truth[later]) > 0.05
