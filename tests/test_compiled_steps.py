"""The small trainers' steps (SFT, reward model, GRPO) compile like the world model's: explicit
in/out shardings on the mesh, the state donated, traced inside JAX's mesh context so
``sharding.constrain`` is live (8 fake CPU devices, tests/conftest.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from jax.sharding import NamedSharding, PartitionSpec

from sword_jax import sharding as shd
from sword_jax.rl import grpo
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, PolicyConfig, RewardModelConfig, RLConfig
from sword_jax.rl.learned_simulator import toy_reward_model, toy_simulator, toy_start_states
from sword_jax.rl.policy import build_policy, tokenize_instructions
from sword_jax.rl.sft import make_sft_step

CFG = RLConfig(image_size=8, action_bins=8, chunk_len=4, proprio_dim=4,
               policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=16, proprio_encoding="raw"),
               reward_model=RewardModelConfig(width=4), grpo=GRPOConfig(group_size=2, ppo_epochs=1),
               imagined=ImaginedConfig(max_chunks=2))
BATCH_AXES = ("data", "fsdp")


@pytest.fixture(scope="module")
def policy():
    return build_policy(CFG, seed=0)  # the steps below never donate these arrays (copies go in)


def _mesh():
    return shd.make_mesh(shd.MeshConfig(data=2, fsdp=2, tensor=2))


def _spec(sharding) -> PartitionSpec:
    assert isinstance(sharding, NamedSharding), sharding
    return sharding.spec


def test_constrain_reads_jax_mesh_context():
    """``constrain`` follows JAX's own mesh context: ``jax.set_mesh`` alone activates it, and a
    function jitted outside the mesh traces again inside it (module globals did neither)."""
    mesh = _mesh()
    shard = jax.jit(lambda x: shd.constrain(x * 2.0, ("batch", None)))
    x = jnp.ones((8, 2))
    assert len(shard(x).sharding.device_set) == 1  # no mesh: a no-op
    with jax.set_mesh(mesh):
        assert _spec(shard(x).sharding) == PartitionSpec(BATCH_AXES)
    with shd.use_mesh(mesh, (("batch", ("data",)),)):
        assert jax.sharding.get_abstract_mesh() == mesh.abstract_mesh
        assert _spec(jax.jit(lambda x: shd.constrain(x + 1.0, ("batch", None)))(x).sharding) == PartitionSpec("data")
    assert jax.sharding.get_abstract_mesh().empty and shd.active_rules() == shd.DEFAULT_RULES


def test_sft_step_keeps_sharded_params_splits_the_batch_and_donates(policy):
    mesh = _mesh()
    graphdef, params = policy
    params = jax.device_put(params, shd.state_shardings(nnx.eval_shape(lambda: params), mesh, shd.DEFAULT_RULES))
    intended = jax.tree.map(lambda x: x.sharding, params)
    assert any(_spec(s) != PartitionSpec() for s in jax.tree.leaves(intended))  # really sharded
    init, step = make_sft_step(graphdef, CFG, total_steps=4, mesh=mesh)
    rng = np.random.default_rng(0)
    batch = {"frames": rng.random((4, 8, 8, 3), np.float32),
             "instruction_tokens": tokenize_instructions(["pick", "place", "open", "close"], 16),
             "proprio": rng.random((4, 4), np.float32), "actions": rng.uniform(-1, 1, (4, 4, 7)).astype(np.float32)}
    state, metrics = step(init(params), batch, jax.random.key(0))
    for want, got in zip(jax.tree.leaves(intended), jax.tree.leaves(state.params)):
        assert got.sharding == want
    assert all(_spec(m.sharding) == PartitionSpec() and len(m.sharding.device_set) == 8 for m in metrics.values())
    compiled = step.lower(state, batch, jax.random.key(0)).compile()  # the executable the call built
    assert _spec(compiled.input_shardings[0][1]["frames"]) == PartitionSpec(BATCH_AXES)
    step(state, batch, jax.random.key(1))
    assert all(x.is_deleted() for x in jax.tree.leaves(state))  # donated


def test_grpo_step_constrains_activations_on_the_mesh(policy):
    """The GRPO step used to run outside any mesh, so its rollout's ``constrain`` calls were no-ops."""
    mesh = _mesh()
    graphdef, params = policy
    sim, reward_model = toy_simulator(frame_size=8, chunk_len=4, proprio_dim=4), toy_reward_model()
    tokens = jnp.asarray(tokenize_instructions(["pick", "place", "open", "close"], 16))
    start = toy_start_states(tokens, key=jax.random.key(1), frame_size=8, proprio_dim=4)
    step = grpo.make_grpo_step(graphdef, CFG, mesh=mesh)
    lowered = step.lower(grpo.init_state(params, CFG), (sim, reward_model, start), jax.random.key(0))
    text = lowered.as_text()
    assert "sharding_constraint" in text or "@Sharding" in text
