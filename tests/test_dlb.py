"""Dynamic Latent Bootstrapping: schedules, reads seen by a probe model, writes, sharding, persistence."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax import checkpoint
from sword_jax.dlb import cache as dlb_cache
from sword_jax.dlb import schedule
from sword_jax.dlb.config import CacheConfig
from tests.support.world_model import ProbeWorldModel, build, full_mesh, single_device_mesh, tiny_dataset

F32_CACHE = dict(dtype="float32")


def test_schedule_values_at_known_steps():
    linear = CacheConfig(schedule="linear", read_prob_start=0.0, read_prob_end=0.5, schedule_steps=100)
    for step, value in [(0, 0.0), (50, 0.25), (100, 0.5), (400, 0.5)]:
        np.testing.assert_allclose(schedule.read_prob(linear, step), value, atol=1e-6)
    np.testing.assert_allclose(schedule.teacher_forcing_share(linear, 50), 0.75, atol=1e-6)
    cosine = CacheConfig(schedule="warmup_cosine", read_prob_start=0.1, read_prob_end=0.9, schedule_steps=100,
                         warmup_steps=10)
    for step, value in [(0, 0.1), (10, 0.1), (60, 0.5), (35, 0.1 + 0.8 * (1 - np.cos(np.pi * 0.25)) / 2),
                        (110, 0.9), (1000, 0.9)]:
        np.testing.assert_allclose(schedule.read_prob(cosine, step), value, atol=1e-6)
    with pytest.raises(ValueError, match="schedule"):
        CacheConfig(schedule="step").validate()


def _filled_cache(state, shardings, values, filled):
    return state.replace(cache=dlb_cache.LatentCache(
        latents=jax.device_put(jnp.asarray(values, state.cache.latents.dtype), shardings.cache.latents),
        filled=jax.device_put(jnp.asarray(filled), shardings.cache.filled)))


@pytest.mark.parametrize("read_prob", [0.0, 1.0])
def test_probe_sees_cached_context_iff_read(read_prob, key):
    mesh = single_device_mesh()
    cfg = CacheConfig(read_prob_start=read_prob, read_prob_end=read_prob, **F32_CACHE)
    _, state, shardings, step, loader = build(mesh=mesh, cache_cfg=cfg, model_cls=ProbeWorldModel)
    shape = state.cache.latents.shape
    values = 100.0 + np.arange(np.prod(shape), dtype=np.float32).reshape(shape)
    filled = np.ones(shape[:2], bool)
    filled[::2] = False  # even episodes: nothing cached -> never read
    state = _filled_cache(state, shardings, values, filled)
    batch = loader.next()
    ProbeWorldModel.records.clear()
    state, metrics = step(state, batch, key)
    jax.block_until_ready(metrics)
    seen_context = ProbeWorldModel.records[-1][0][:, 1]
    episodes, starts = np.asarray(batch["episode"]), np.asarray(batch["start"])
    ground_truth = np.asarray(batch["latents"])[:, 1]
    for i, (episode, start) in enumerate(zip(episodes, starts)):
        expected = values[episode, start] if (read_prob == 1.0 and filled[episode, start]) else ground_truth[i]
        np.testing.assert_array_equal(seen_context[i], expected)
    expected_share = np.mean(filled[episodes, starts]) if read_prob == 1.0 else 0.0
    np.testing.assert_allclose(metrics["read_share"], expected_share)


def _cache(num_episodes=4, num_latents=6, dtype="float32", filled_value=False):
    cfg = CacheConfig(dtype=dtype)
    cache = dlb_cache.init_cache(cfg, (num_episodes, num_latents, 2, 2, 3))
    return cache.replace(latents=cache.latents + 1.0, filled=jnp.full_like(cache.filled, filled_value))


def test_ema_arithmetic_and_empty_slot_takes_prediction():
    cfg = CacheConfig(replacement="ema", ema_rate=0.25, scope="all", dtype="float32")
    cache = _cache()
    cache = cache.replace(filled=cache.filled.at[0, 3].set(True))
    predictions = jnp.stack([jnp.full((2, 2, 3), 5.0), jnp.full((2, 2, 3), 9.0)])[None]  # (1, 2, h, w, c)
    out = dlb_cache.write_predictions(cache, cfg, predictions, jnp.array([0]), jnp.array([3]))
    np.testing.assert_allclose(out.latents[0, 3], 0.75 * 1.0 + 0.25 * 5.0)  # filled: EMA
    np.testing.assert_allclose(out.latents[0, 4], 9.0)  # empty: direct
    assert bool(out.filled[0, 3]) and bool(out.filled[0, 4])


@pytest.mark.parametrize("scope", ["single", "all"])
def test_scope_writes_exactly_the_right_slots(scope):
    cfg = CacheConfig(scope=scope, dtype="float32")
    cache = _cache()
    predictions = jnp.arange(2 * 2 * 2 * 2 * 3, dtype=jnp.float32).reshape(2, 2, 2, 2, 3) + 50.0
    episodes, first_future = jnp.array([1, 3]), jnp.array([2, 4])
    out = dlb_cache.write_predictions(cache, cfg, predictions, episodes, first_future)
    written = {(1, 2): predictions[0, 0], (3, 4): predictions[1, 0]}
    if scope == "all":
        written.update({(1, 3): predictions[0, 1], (3, 5): predictions[1, 1]})
    for e in range(4):
        for j in range(6):
            if (e, j) in written:
                np.testing.assert_array_equal(out.latents[e, j], written[(e, j)])
                assert bool(out.filled[e, j])
            else:
                np.testing.assert_array_equal(out.latents[e, j], cache.latents[e, j])
                assert not bool(out.filled[e, j])
    gated = dlb_cache.write_predictions(cache, cfg, predictions, episodes, first_future, enabled=False)
    np.testing.assert_array_equal(gated.latents, cache.latents)
    assert not np.any(gated.filled)


def test_duplicate_slot_last_sample_in_batch_wins():
    cfg = CacheConfig(scope="all", dtype="float32")
    predictions = jnp.stack([jnp.full((2, 2, 2, 3), float(v)) for v in (10, 20, 30)])
    out = dlb_cache.write_predictions(_cache(), cfg, predictions, jnp.array([2, 2, 2]), jnp.array([1, 2, 1]))
    np.testing.assert_array_equal(out.latents[2, 1], 30.0)  # samples 0 and 2 write (2,1): sample 2 wins
    np.testing.assert_array_equal(out.latents[2, 2], 30.0)  # samples 0,1,2 write (2,2): sample 2 wins
    np.testing.assert_array_equal(out.latents[2, 3], 20.0)  # only sample 1 writes (2,3)


def test_sharded_cache_equals_single_device_and_stays_local(keys):
    cfg = CacheConfig(replacement="ema", dtype="float32")
    shape = (16, 6, 2, 2, 3)
    values = jax.random.normal(keys[0], shape)
    filled = jax.random.bernoulli(keys[1], 0.5, shape[:2])
    predictions = jax.random.normal(keys[2], (8, 2, 2, 2, 3))
    context = jax.random.normal(keys[3], (8, 1, 2, 2, 3))
    episodes = jnp.array([0, 3, 3, 7, 9, 12, 15, 15], jnp.int32)
    starts = jnp.array([1, 2, 2, 3, 1, 2, 3, 1], jnp.int32)

    def fn(cache, ctx, e, s, pred, key):
        read, mask = dlb_cache.read_context(cache, ctx, e, s[:, None], jnp.float32(0.7), key=key)
        return dlb_cache.write_predictions(cache, cfg, pred, e, s + 1), read, mask

    single = jax.jit(fn)(dlb_cache.LatentCache(values, filled), context, episodes, starts, predictions, keys[4])
    mesh = full_mesh()
    sh = dlb_cache.cache_shardings(shape, mesh)
    assert sh.latents.spec[0] is not None  # really sharded over episodes
    sharded_cache = dlb_cache.LatentCache(jax.device_put(values, sh.latents), jax.device_put(filled, sh.filled))
    sharded_fn = jax.jit(fn, out_shardings=(sh, None, None), donate_argnums=(0,))
    hlo = sharded_fn.lower(sharded_cache, context, episodes, starts, predictions, keys[4]).compile().as_text()
    sharded = sharded_fn(sharded_cache, context, episodes, starts, predictions, keys[4])
    for a, b in zip(jax.tree.leaves(single), jax.tree.leaves(sharded)):
        np.testing.assert_array_equal(a, b)
    assert sharded[0].latents.sharding.spec == sh.latents.spec
    # no collective ever moves a whole (or per-device) cache slice
    per_device_elems = shape[0] // 8 * np.prod(shape[1:])
    for line in hlo.splitlines():
        if any(op in line for op in ("all-gather(", "all-to-all(", "collective-permute(")):
            dims = line.split("=")[1].split("[")[1].split("]")[0]
            assert np.prod([int(d) for d in dims.split(",") if d]) < per_device_elems, line


def test_cache_bytes_for_the_paper_dataset():
    mesh = full_mesh()
    paper = (1500, 128, 16, 16, 48)
    bf16 = dlb_cache.cache_bytes_per_device(CacheConfig(dtype="bfloat16"), paper, mesh)
    episodes_per_device = -(-1500 // 8)
    assert bf16 == episodes_per_device * 128 * (16 * 16 * 48 * 2 + 1)
    assert bf16 * 8 <= 5e9
    f32 = dlb_cache.cache_bytes_per_device(CacheConfig(dtype="float32"), paper, None)
    assert f32 == 1500 * 128 * (16 * 16 * 48 * 4 + 1)


def test_dlb_step_sharded_equals_single_device_and_traces_once(key):
    cfg = CacheConfig(read_prob_start=0.6, read_prob_end=0.9, schedule_steps=4, **F32_CACHE)
    results = []
    for mesh in (single_device_mesh(), full_mesh()):
        chex.clear_trace_counter()  # the counter is keyed by function name; count per mesh
        _, state, _, step, loader = build(mesh=mesh, cache_cfg=cfg,
                                          wrap=lambda fn: chex.assert_max_traces(fn, n=1))
        for _ in range(4):
            state, metrics = step(state, loader.next(), key)
        results.append(jax.device_get((state.params, state.cache, metrics)))
    chex.clear_trace_counter()
    (p1, c1, m1), (p8, c8, m8) = results
    assert m1["read_share"] > 0  # the cache was really read
    chex.assert_trees_all_close(p1, p8, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(c1.filled, c8.filled)
    np.testing.assert_allclose(c1.latents, c8.latents, rtol=1e-5, atol=1e-5)


def test_read_prob_zero_is_bitwise_teacher_forcing(key):
    mesh = single_device_mesh()
    out = []
    for cfg in (CacheConfig(enabled=False), CacheConfig(read_prob_start=0.0, read_prob_end=0.0)):
        _, state, _, step, loader = build(mesh=mesh, cache_cfg=cfg)
        for _ in range(3):
            state, metrics = step(state, loader.next(), key)
        out.append(jax.device_get((state.params, state.opt_state, metrics["loss"])))
    for a, b in zip(jax.tree.leaves(out[0]), jax.tree.leaves(out[1])):
        np.testing.assert_array_equal(a, b)


def test_cache_bit_identical_after_save_and_restore(tmp_path, key):
    mesh = full_mesh()
    _, state, shardings, step, loader = build(mesh=mesh, cache_cfg=CacheConfig())
    for _ in range(2):
        state, _ = step(state, loader.next(), key)
    assert state.cache.latents.dtype == jnp.bfloat16 and bool(jnp.any(state.cache.filled))
    ckpt = checkpoint.Checkpointer(str(tmp_path / "ckpt"))
    ckpt.save(2, state, {"data_position": loader.position})
    restored, meta = ckpt.restore(checkpoint.abstract_like(state, shardings))
    ckpt.close()
    assert meta["data_position"] == loader.position
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(restored)):
        assert a.dtype == b.dtype and a.sharding == b.sharding
        np.testing.assert_array_equal(np.asarray(a.astype(jnp.float32) if a.dtype == jnp.bfloat16 else a),
                                      np.asarray(b.astype(jnp.float32) if b.dtype == jnp.bfloat16 else b))


def test_empty_dataset_shape_is_rejected():
    with pytest.raises(ValueError, match="dataset_shape"):
        dlb_cache.cache_shape((0, 4, 2, 2, 3), None)
    assert tiny_dataset().shape == (8, 6, 2, 2, 8)


def test_ablation_configs_cover_the_eight_designs_and_baselines():
    from configs import cache_ablation

    seen = set()
    for design in cache_ablation.DESIGNS:
        cfg = configs_get(f"cache_ablation:{design}")
        assert cfg.cache.enabled
        seen.add((cfg.cache.schedule, cfg.cache.replacement, cfg.cache.scope))
    assert len(seen) == 8
    best, default = configs_get("cache_ablation:linear-direct-all").cache, CacheConfig()
    design = lambda c: (c.enabled, c.schedule, c.replacement, c.scope)  # noqa: E731
    assert design(best) == design(default) == (True, "linear", "direct", "all")  # the default = paper's best
    tf, wovr = configs_get("cache_ablation:tf"), configs_get("cache_ablation:wovr")
    assert not tf.cache.enabled and tf.flow.context_noise == 0.0
    assert not wovr.cache.enabled and wovr.flow.context_noise > 0.0


def configs_get(name):
    import configs

    return configs.get(name)
