"""Shifted Euler sampler: hand-computed steps, conditioning re-imposed, guidance, epsilon conversion."""

import jax
import jax.numpy as jnp
import jax.extend.core as jax_core
import numpy as np
import pytest
from flax import nnx

from sword_jax.world_model import flow, sampler
from sword_jax.world_model.config import FlowConfig
from tests.support.world_model import MixerWorldModel, ProbeWorldModel


def _inputs(keys, batch=2, cond=2, future=2):
    cond_latents = jax.random.normal(keys[0], (batch, cond, 2, 2, 8))
    actions = jax.random.uniform(keys[1], (batch, 1 + 4 * (cond + future - 1), 7), minval=-1.0, maxval=1.0)
    noise = jax.random.normal(keys[2], (batch, future, 2, 2, 8))
    return cond_latents, actions, noise


def test_one_step_equals_hand_computed_euler(keys):
    model = MixerWorldModel(rngs=nnx.Rngs(0))
    cond, actions, noise = _inputs(keys)
    cfg = FlowConfig(shift=3.0)
    out = sampler.sample(model, cond, actions, key=keys[3], num_future=2, cfg=cfg, num_steps=1, noise=noise)
    timesteps = jnp.array([[0.0, 0.0, 1000.0, 1000.0]] * 2, jnp.float32)
    velocity = model(jnp.concatenate([cond, noise], axis=1), timesteps, actions)[:, 2:]
    np.testing.assert_allclose(out, noise - velocity, rtol=1e-5, atol=1e-5)  # x0 = x1 + (0 - 1) v


def test_two_steps_hand_computed_and_conditioning_reimposed(keys):
    ProbeWorldModel.records.clear()
    model = ProbeWorldModel(rngs=nnx.Rngs(1))
    cond, actions, noise = _inputs(keys)
    cfg = FlowConfig(shift=5.0)
    out = jax.jit(lambda c, a, n: sampler.sample(model, c, a, key=keys[3], num_future=2, cfg=cfg, num_steps=2,
                                                 noise=n))(cond, actions, noise)
    jax.block_until_ready(out)
    seen = ProbeWorldModel.records[-2:]
    for latents, timesteps in seen:
        np.testing.assert_array_equal(latents[:, :2], np.asarray(cond))
        assert np.all(timesteps[:, :2] == 0)
    sig = np.asarray(flow.sampling_sigmas(2, 5.0))
    np.testing.assert_allclose(seen[0][1][:, 2:], sig[0] * 1000.0, rtol=1e-6)
    np.testing.assert_allclose(seen[1][1][:, 2:], sig[1] * 1000.0, rtol=1e-6)
    x = np.asarray(noise)
    for i in range(2):
        t = jnp.concatenate([jnp.zeros((2, 2)), jnp.full((2, 2), sig[i] * 1000.0)], axis=1).astype(jnp.float32)
        v = MixerWorldModel.__call__(model, jnp.concatenate([cond, jnp.asarray(x)], axis=1), t, actions)[:, 2:]
        x = x + (sig[i + 1] - sig[i]) * np.asarray(v)
    np.testing.assert_allclose(out, x, rtol=1e-4, atol=1e-4)


def test_the_sampling_shift_sets_the_grid_and_defaults_to_the_training_shift(keys):
    """flow.sample_shift moves the sampler's noise levels (the model is called at the levels of that shift, the
    training's shift left as it is); 0 keeps the training's, bit for bit."""
    cond, actions, noise = _inputs(keys)
    seen = {}
    for name, cfg in {"default": FlowConfig(shift=5.0), "same": FlowConfig(shift=5.0, sample_shift=5.0),
                      "uniform": FlowConfig(shift=5.0, sample_shift=1.0)}.items():
        ProbeWorldModel.records.clear()
        out = sampler.sample(ProbeWorldModel(rngs=nnx.Rngs(1)), cond, actions, key=keys[3], num_future=2, cfg=cfg,
                             num_steps=5, noise=noise)
        seen[name] = (np.asarray(out), [float(t[0, -1]) for _, t in ProbeWorldModel.records[-5:]])
    np.testing.assert_array_equal(seen["default"][0], seen["same"][0])
    np.testing.assert_allclose(seen["default"][1], np.asarray(flow.sampling_sigmas(5, 5.0))[:-1] * 1000, rtol=1e-6)
    np.testing.assert_allclose(seen["uniform"][1], [1000.0, 800.0, 600.0, 400.0, 200.0], rtol=1e-6)
    assert seen["default"][1][-1] == pytest.approx(1000 * 5 * 0.2 / (1 + 4 * 0.2), rel=1e-6)  # the last step: 0.56
    assert not np.allclose(seen["uniform"][0], seen["default"][0])
    for bad in (-1.0, float("nan"), 101.0):
        with pytest.raises(ValueError, match="flow.sample_shift"):
            FlowConfig(sample_shift=bad).validate()


def test_guidance_combines_conditional_and_null_actions(keys):
    model = MixerWorldModel(rngs=nnx.Rngs(2))
    cond, actions, noise = _inputs(keys)
    cfg = FlowConfig()
    kwargs = dict(key=keys[3], num_future=2, cfg=cfg, num_steps=1, noise=noise)
    conditional = sampler.sample(model, cond, actions, guidance_scale=1.0, **kwargs)
    unconditional = sampler.sample(model, cond, jnp.zeros_like(actions), guidance_scale=1.0, **kwargs)
    guided = sampler.sample(model, cond, actions, guidance_scale=3.0, **kwargs)
    # one Euler step is affine in v, so x(g) = x_null + g (x_cond - x_null)
    np.testing.assert_allclose(guided, unconditional + 3.0 * (conditional - unconditional), rtol=1e-4, atol=1e-4)
    assert not np.allclose(guided, conditional)


def test_epsilon_prediction_converts_to_velocity(keys):
    model = MixerWorldModel(rngs=nnx.Rngs(3))
    cond, actions, noise = _inputs(keys)
    cfg = FlowConfig(prediction="epsilon", shift=1.0)
    out = sampler.sample(model, cond, actions, key=keys[3], num_future=2, cfg=cfg, num_steps=2, noise=noise)
    x = noise
    for s, s_next in [(1.0, 0.5), (0.5, 0.0)]:
        t = jnp.concatenate([jnp.zeros((2, 2)), jnp.full((2, 2), s * 1000.0)], axis=1).astype(jnp.float32)
        eps = model(jnp.concatenate([cond, x], axis=1), t, actions)[:, 2:]
        v = (eps - x) / max(1.0 - s, 1e-3)
        x = x + (s_next - s) * v
    np.testing.assert_allclose(out, x, rtol=1e-4, atol=1e-4)
    assert np.all(np.isfinite(out))


def test_sampler_rejects_bad_inputs(keys):
    model = MixerWorldModel(rngs=nnx.Rngs(0))
    cond, actions, _ = _inputs(keys)
    with pytest.raises(ValueError, match="actions"):
        sampler.sample(model, cond, actions[:, :-1], key=keys[0], num_future=2, cfg=FlowConfig())
    with pytest.raises(ValueError, match="num_steps"):
        sampler.sample(model, cond, actions, key=keys[0], num_future=2, cfg=FlowConfig(), num_steps=51)


def test_noise_scale_scales_the_starting_noise(keys):
    """``flow.noise_scale`` starts the Euler path from ``scale * noise``, drawn or given: 0 gives one prediction per
    condition whatever the key, 1 leaves the sample (and its jaxpr) as it was."""
    import dataclasses

    model = MixerWorldModel(rngs=nnx.Rngs(4))
    cond, actions, noise = _inputs(keys)
    base = FlowConfig(shift=3.0)
    kw = dict(num_future=2, num_steps=3)
    for scale in (0.5, 0.0, 2.0):
        cfg = dataclasses.replace(base, noise_scale=scale)
        scaled = sampler.sample(model, cond, actions, key=keys[3], cfg=cfg, noise=noise, **kw)
        by_hand = sampler.sample(model, cond, actions, key=keys[3], cfg=base, noise=scale * noise, **kw)
        np.testing.assert_allclose(scaled, by_hand, rtol=1e-6, atol=1e-6)
        drawn = sampler.sample(model, cond, actions, key=keys[3], cfg=cfg, **kw)  # the key's draw, scaled
        first = jax.random.normal(keys[3], noise.shape, jnp.float32)
        np.testing.assert_allclose(drawn, sampler.sample(model, cond, actions, key=keys[0], cfg=base,
                                                         noise=scale * first, **kw), rtol=1e-6, atol=1e-6)
    zero = dataclasses.replace(base, noise_scale=0.0)
    a, b = (sampler.sample(model, cond, actions, key=k, cfg=zero, **kw) for k in (keys[0], keys[1]))
    np.testing.assert_array_equal(a, b)
    warm = sampler.sample(model, cond, actions, key=keys[0], cfg=dataclasses.replace(base, noise_scale=0.5), **kw)
    cold = sampler.sample(model, cond, actions, key=keys[1], cfg=dataclasses.replace(base, noise_scale=0.5), **kw)
    assert not np.allclose(warm, cold)  # below 1 and above 0 the key still matters
    def jaxpr(cfg):
        return str(jax.make_jaxpr(lambda n: sampler.sample(model, cond, actions, key=keys[0], cfg=cfg, noise=n, **kw))(
            noise))

    assert jaxpr(dataclasses.replace(base, noise_scale=1.0)) == jaxpr(base)
    assert jaxpr(dataclasses.replace(base, noise_scale=0.5)) != jaxpr(base)
    for bad in (-0.1, 4.5, float("nan")):
        with pytest.raises(ValueError, match="flow.noise_scale"):
            dataclasses.replace(base, noise_scale=bad).validate()


def _dot_generals(jaxpr) -> int:
    """``dot_general`` equations of a jaxpr, those of nested jaxprs (scan bodies, pjit) included."""
    count = 0
    for eqn in jaxpr.eqns:
        count += eqn.primitive.name == "dot_general"
        for sub in jax_core.jaxprs_in_params(eqn.params):
            count += _dot_generals(sub)
    return count


def _euler_body_dot_generals(jaxpr) -> int:
    """Matmuls inside the sampler's Euler-step scan (the outermost ``scan``)."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "scan":
            return _dot_generals(eqn.params["jaxpr"].jaxpr)
        for sub in jax_core.jaxprs_in_params(eqn.params):
            found = _euler_body_dot_generals(sub)
            if found is not None:
                return found
    return None


@pytest.mark.parametrize("guidance", [1.0, 2.5])
def test_actions_conditioned_once_per_chunk_give_the_same_sample(keys, guidance):
    """The tiny world model sampled with the actions' cross-attention keys / values and AdaLN offset computed once
    per chunk equals the sample that recomputes them at every Euler step, and the Euler steps no longer hold those
    matmuls (2 action-token MLP layers, 2 AdaLN layers, the blocks' key and value projections)."""
    import dataclasses

    import configs
    from sword_jax.dit.action_dit import WorldModel

    model_cfg = dataclasses.replace(configs.get("sword:tiny").model, compute_dtype="float32")
    graphdef, state = nnx.split(WorldModel(model_cfg, rngs=nnx.Rngs(0)))
    state = jax.tree.map(lambda x: x + 0.1 * jax.random.normal(keys[4], x.shape, x.dtype), state)  # non-zero heads
    cond = jax.random.normal(keys[0], (2, 2, 4, 4, model_cfg.in_dim))
    actions = jax.random.uniform(keys[1], (2, 1 + 4 * 3, model_cfg.action_dim), minval=-1.0, maxval=1.0)
    cfg = FlowConfig(shift=3.0, guidance_scale=guidance)

    def run(cache_actions):
        model_fn = sampler.model_fn_from_state(graphdef, state, cache_actions=cache_actions)
        return lambda c, a: sampler.sample(model_fn, c, a, key=keys[2], num_future=2, cfg=cfg, num_steps=3)

    cached, plain = run(True), run(False)
    np.testing.assert_allclose(np.asarray(jax.jit(cached)(cond, actions)), np.asarray(jax.jit(plain)(cond, actions)),
                               rtol=1e-5, atol=1e-5)
    in_steps = {name: _euler_body_dot_generals(jax.make_jaxpr(fn)(cond, actions).jaxpr)
                for name, fn in (("cached", cached), ("plain", plain))}
    assert in_steps["plain"] - in_steps["cached"] == 2 + 2 + 2  # token MLP, AdaLN MLP, k and v (scanned blocks)
