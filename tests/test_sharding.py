import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from sword_jax import sharding


class TinyMLP(nnx.Module):
    def __init__(self, dim: int, hidden: int, *, rngs: nnx.Rngs):
        init = nnx.initializers.lecun_normal()
        self.up = nnx.Linear(dim, hidden, kernel_init=nnx.with_partitioning(init, ("embed", "mlp")),
                             bias_init=nnx.with_partitioning(nnx.initializers.normal(0.1), ("mlp",)), rngs=rngs)
        self.down = nnx.Linear(hidden, dim, kernel_init=nnx.with_partitioning(init, ("mlp", "embed")), rngs=rngs)

    def __call__(self, x):
        h = sharding.constrain(jax.nn.gelu(self.up(x)), ("batch", "mlp"))
        return sharding.constrain(self.down(h), ("batch", "embed"))


def _forward(graphdef, state, x):
    return nnx.merge(graphdef, state)(x)


def test_mesh_shape_resolves_rest():
    assert sharding.mesh_shape(sharding.MeshConfig(data=-1, fsdp=2, tensor=2), 8) == (2, 2, 2)
    assert sharding.mesh_shape(sharding.MeshConfig(data=2, fsdp=-1, tensor=1), 8) == (2, 4, 1)
    with pytest.raises(ValueError, match="not divisible"):
        sharding.mesh_shape(sharding.MeshConfig(data=-1, fsdp=3), 8)
    with pytest.raises(ValueError, match="at most one"):
        sharding.MeshConfig(data=-1, fsdp=-1).validate()


def test_logical_to_spec_drops_indivisible_dims():
    mesh = sharding.make_mesh(sharding.MeshConfig(data=2, fsdp=2, tensor=2))
    spec = sharding.logical_to_spec(("batch", "embed"), sharding.DEFAULT_RULES, mesh, (8, 6))
    assert spec == jax.sharding.PartitionSpec(("data", "fsdp"), None) or spec == jax.sharding.PartitionSpec(("data", "fsdp"))
    spec = sharding.logical_to_spec(("batch",), sharding.DEFAULT_RULES, mesh, (3,))
    assert spec == jax.sharding.PartitionSpec()


def test_sharded_init_and_forward_match_single_device():
    assert jax.device_count() == 8, "conftest must provide 8 fake CPU devices"
    factory = lambda: TinyMLP(16, 32, rngs=nnx.Rngs(0))
    x = jax.random.normal(jax.random.key(1), (8, 16))

    mesh = sharding.make_mesh(sharding.MeshConfig(data=2, fsdp=2, tensor=2))
    graphdef, state = sharding.create_sharded(factory, mesh, sharding.DEFAULT_RULES)
    kernel = state["up"]["kernel"].get_value()
    assert kernel.sharding.spec == jax.sharding.PartitionSpec("fsdp", "tensor")
    assert len({str(s.index) for s in kernel.addressable_shards}) == 4  # really split, not replicated
    with sharding.use_mesh(mesh):
        x_sharded = jax.device_put(x, sharding.batch_sharding(mesh, 2))
        y_sharded = jax.jit(_forward, static_argnums=0)(graphdef, state, x_sharded)

    one = sharding.make_mesh(sharding.MeshConfig(data=1), devices=jax.devices()[:1])
    graphdef1, state1 = sharding.create_sharded(factory, one, sharding.DEFAULT_RULES)
    y_single = jax.jit(_forward, static_argnums=0)(graphdef1, state1, x)

    np.testing.assert_array_equal(np.asarray(state["up"]["kernel"].get_value()), np.asarray(state1["up"]["kernel"].get_value()))
    np.testing.assert_allclose(np.asarray(y_sharded), np.asarray(y_single), rtol=1e-5, atol=1e-6)
    assert not np.allclose(np.asarray(y_single), 0.0)
