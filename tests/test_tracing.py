"""The per-function retrace guard used by the VAE and GRPO steps."""

import jax
import jax.numpy as jnp
import pytest

from sword_jax import tracing


def _make():
    def step(x):
        return x * 2

    return jax.jit(tracing.max_traces(step, n=1))


def test_each_built_step_has_its_own_count():
    # Two runs in one process build the same step twice (train.compare); neither is a retrace.
    for _ in range(2):
        step = _make()
        step(jnp.ones(3))
        step(jnp.ones(3))


def test_a_retrace_names_the_function_and_the_bound():
    step = _make()
    step(jnp.ones(3))
    with pytest.raises(RuntimeError, match="step was traced 2 times .at most 1"):
        step(jnp.ones(4))


@pytest.mark.slow  # 35-45 s on 2 cores; the per-build trace count is checked by the tests above
def test_vae_step_built_twice_in_one_process_trains():
    from sword_jax.vae import train as vae_train
    from sword_jax.vae.config import VAEConfig

    cfg = VAEConfig(dim=4, dec_dim=4, z_dim=4, dim_mult=(1, 1, 1, 1), num_res_blocks=1, batch_size=1)
    video = jax.random.uniform(jax.random.key(0), (1, 5, 32, 32, 3), jnp.float32, -1, 1)
    for _ in range(2):
        graphdef, state = vae_train.init_train_state(cfg, key=jax.random.key(0))
        step = vae_train.make_vae_step(graphdef, cfg)
        for _ in range(2):
            state, metrics = step(state, {"video": video}, jax.random.key(1))
        assert jnp.isfinite(metrics["loss"])


def test_settle_keeps_values_and_shardings():
    import numpy as np
    from jax.sharding import NamedSharding, PartitionSpec

    from sword_jax import sharding as shd

    mesh = shd.make_mesh(shd.MeshConfig(data=-1))
    target = NamedSharding(mesh, PartitionSpec("data"))
    tree = {"a": jax.device_put(np.arange(16, dtype=np.float32), target), "b": jnp.int32(3)}
    settled = shd.settle(tree)
    assert settled["a"].sharding == target
    np.testing.assert_array_equal(np.asarray(settled["a"]), np.arange(16, dtype=np.float32))
    assert int(settled["b"]) == 3
