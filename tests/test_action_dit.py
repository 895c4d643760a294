"""WorldModel: dual action conditioning, official loading, scan/remat/sharding/bf16 equivalences."""

import dataclasses
import functools
import os

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from sword_jax import sharding
from sword_jax.convert import wan22_dit
from sword_jax.dit.config import DiTConfig
from sword_jax.dit.model import WanDiT
from sword_jax.convert.wan22_dit import load_official_into_world_model
from sword_jax.dit.action_dit import WorldModel, action_chunks, num_video_frames, world_model_apply

CFG = dataclasses.replace(configs.get("sword:tiny").model, compute_dtype="float32")
apply = jax.jit(world_model_apply, static_argnums=0)


def _inputs(seed: int, batch: int = 2, frames: int = 3, size: int = 4, cfg: DiTConfig = CFG):
    k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
    latents = jax.random.normal(k1, (batch, frames, size, size, cfg.in_dim))
    timesteps = jnp.concatenate([jnp.zeros((batch, 1)), jax.random.uniform(k2, (batch, frames - 1)) * 1000], 1)
    actions = jax.random.normal(k3, (batch, num_video_frames(frames), cfg.action_dim))
    return latents, timesteps, actions


@functools.lru_cache
def _randomized(cfg: DiTConfig, seed: int = 0):
    """A WorldModel whose every parameter (zero-initialised ones included) is perturbed."""

    graphdef, state = nnx.split(WorldModel(cfg, rngs=nnx.Rngs(seed)))
    leaves, treedef = jax.tree.flatten(state)
    rng = np.random.default_rng(seed)
    leaves = [x + jnp.asarray(0.2 * rng.standard_normal(x.shape), x.dtype) for x in leaves]
    return graphdef, jax.tree.unflatten(treedef, leaves)


@functools.lru_cache
def _graphdef(cfg: DiTConfig) -> nnx.GraphDef:
    return nnx.graphdef(sharding.abstract_module(lambda: WorldModel(cfg, rngs=nnx.Rngs(0))))


def _max_diff(a, b) -> float:
    return float(jnp.max(jnp.abs(a - b)))


def test_action_chunks_layout():
    actions = jnp.arange(9 * 2, dtype=jnp.float32).reshape(1, 9, 2) + 1
    chunks = action_chunks(actions)  # (1, 3, 8)
    np.testing.assert_array_equal(chunks[0, 0], [0, 0, 0, 0, 0, 0, 1, 2])  # frame 0: zero-padded in front
    np.testing.assert_array_equal(chunks[0, 1], np.arange(3, 11))  # video frames 1..4
    np.testing.assert_array_equal(chunks[0, 2], np.arange(11, 19))  # video frames 5..8


@pytest.mark.parametrize("cross_attn,adaln", [(True, True), (True, False), (False, True), (False, False)])
def test_each_action_branch_carries_information(cross_attn, adaln):
    cfg = dataclasses.replace(CFG, action_cross_attn=cross_attn, action_adaln=adaln)
    graphdef, state = _randomized(cfg)
    latents, timesteps, actions = _inputs(0)
    other = actions + jax.random.normal(jax.random.key(9), actions.shape)
    out = apply(graphdef, state, latents, timesteps, actions)
    out_other = apply(graphdef, state, latents, timesteps, other)
    assert out.shape == latents.shape and out.dtype == jnp.float32
    assert bool(jnp.all(jnp.isfinite(out)))
    if cross_attn or adaln:
        assert _max_diff(out, out_other) > 1e-2, "actions do not reach the output"
    else:
        assert _max_diff(out, out_other) == 0.0, "actions leak into the output with both branches off"
    # the latents always matter
    assert _max_diff(out, apply(graphdef, state, latents * 0.5, timesteps, actions)) > 1e-2


@pytest.fixture(scope="module")
def weights(shared_dir):
    return os.path.join(shared_dir, "reference", "wan22", "dit_weights.safetensors")


def _grads(graphdef, state, latents, timesteps, actions) -> dict:
    def loss(state):
        return jnp.mean(jnp.square(world_model_apply(graphdef, state, latents, timesteps, actions)))

    return {p: v.get_value() for p, v in nnx.to_flat_state(jax.jit(jax.grad(loss))(state))}


def test_load_official_into_world_model(weights):
    official_cfg, _, official_state = wan22_dit.load_official(weights)
    cfg, graphdef, state = load_official_into_world_model(weights, dataclasses.replace(official_cfg, compute_dtype="float32"))
    # every shared parameter is the official one
    ours = dict(nnx.to_flat_state(state))
    for path, value in nnx.to_flat_state(official_state):
        np.testing.assert_array_equal(ours[("dit",) + path].get_value(), value.get_value())
    branch = {p[1:]: v.get_value() for p, v in ours.items() if p[0] != "dit"}
    assert {p[0] for p in branch} == {"token_in", "token_out", "chunk_in", "chunk_out"}
    assert float(jnp.abs(branch[("chunk_out", "kernel")]).max()) == 0.0  # AdaLN branch starts neutral
    assert float(jnp.abs(branch[("token_in", "kernel")]).max()) > 0.0

    latents, timesteps, actions = _inputs(1)
    grads = _grads(graphdef, state, latents, timesteps, actions)
    for path in [("chunk_out", "kernel"), ("token_in", "kernel"), ("token_out", "kernel")]:
        assert float(jnp.abs(grads[("actions",) + path]).max()) > 0.0, f"no gradient reaches {path}"

    # the AdaLN branch is neutral at load (zero-init) and informative after one gradient step
    model = nnx.merge(graphdef, state)
    other = actions + 1.0
    assert _max_diff(model.actions.time_offset(actions), 0.0) == 0.0
    model.actions.chunk_out.kernel[...] = model.actions.chunk_out.kernel[...] - grads[("actions", "chunk_out", "kernel")]
    assert _max_diff(model.actions.time_offset(actions), model.actions.time_offset(other)) > 1e-6

    with pytest.raises(ValueError, match="differ"):
        load_official_into_world_model(weights, CFG)


def _assert_variants_match_plain(variants):
    graphdef, state = _randomized(CFG)
    latents, timesteps, actions = _inputs(2)

    def loss_fn(cfg):
        graphdef_cfg = _graphdef(cfg)

        def loss(state):
            return jnp.mean(jnp.square(world_model_apply(graphdef_cfg, state, latents, timesteps, actions)))

        return jax.jit(jax.value_and_grad(loss))(state)

    ref_loss, ref_grads = loss_fn(CFG)
    for variant in variants:
        value, grads = loss_fn(dataclasses.replace(CFG, **variant))
        np.testing.assert_allclose(value, ref_loss, rtol=1e-6)
        for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(ref_grads)):
            np.testing.assert_allclose(a, b, atol=1e-6, rtol=1e-5, err_msg=str(variant))


def test_unscanned_forward_matches_scanned():
    graphdef, state = _randomized(CFG)
    inputs = _inputs(2)
    unscanned = _graphdef(dataclasses.replace(CFG, scan_layers=False))
    np.testing.assert_allclose(apply(unscanned, state, *inputs), apply(graphdef, state, *inputs), atol=1e-5, rtol=1e-6)


@pytest.mark.slow
def test_scan_and_remat_variants_match_in_value_and_gradient():
    _assert_variants_match_plain([dict(scan_layers=False), dict(remat="full"), dict(remat="dots"),
                                  dict(remat="dots", scan_layers=False), dict(remat="dots_acts")])


def test_sharded_matches_single_device():
    assert jax.device_count() == 8
    graphdef, state = _randomized(CFG)
    latents, timesteps, actions = _inputs(3, batch=4)
    expected = apply(graphdef, state, latents, timesteps, actions)

    mesh = sharding.make_mesh(sharding.MeshConfig(data=2, fsdp=2, tensor=2))
    shardings = sharding.state_shardings(nnx.eval_shape(lambda: state), mesh, sharding.DEFAULT_RULES)
    sharded_state = jax.device_put(state, shardings)
    q_kernel = sharded_state["dit"]["blocks"]["self_attn"]["q"]["kernel"].get_value()
    assert q_kernel.sharding.spec == jax.sharding.PartitionSpec(None, "fsdp", "tensor")
    with sharding.use_mesh(mesh):
        batch = [jax.device_put(x, sharding.batch_sharding(mesh, x.ndim)) for x in (latents, timesteps, actions)]
        out = jax.jit(world_model_apply, static_argnums=0)(graphdef, sharded_state, *batch)
    np.testing.assert_allclose(out, expected, atol=2e-5, rtol=1e-5)


@pytest.mark.slow
def test_born_sharded_init_matches_plain_init():
    mesh = sharding.make_mesh(sharding.MeshConfig(data=2, fsdp=2, tensor=2))
    factory = lambda: WorldModel(CFG, rngs=nnx.Rngs(5))  # noqa: E731
    _, born = sharding.create_sharded(factory, mesh, sharding.DEFAULT_RULES)
    plain = nnx.split(factory())[1]
    for a, b in zip(jax.tree.leaves(born), jax.tree.leaves(plain)):
        np.testing.assert_allclose(a, b, atol=1e-6)


def test_bfloat16_compute_is_close():
    graphdef, state = _randomized(CFG)
    latents, timesteps, actions = _inputs(4)
    ref = apply(graphdef, state, latents, timesteps, actions)
    graphdef_bf16 = _graphdef(dataclasses.replace(CFG, compute_dtype="bfloat16"))
    out = apply(graphdef_bf16, state, latents, timesteps, actions)
    assert out.dtype == jnp.float32
    rel = _max_diff(out, ref) / float(jnp.max(jnp.abs(ref)))
    assert 0.0 < rel < 5e-2, rel


def test_forward_compiles_once():
    graphdef, state = _randomized(CFG)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def forward(state, latents, timesteps, actions):
        return world_model_apply(graphdef, state, latents, timesteps, actions)

    for seed in range(3):
        forward(state, *_inputs(seed)).block_until_ready()


def test_bad_inputs_are_named():
    model = WorldModel(CFG, rngs=nnx.Rngs(0))
    latents, timesteps, actions = _inputs(0)
    with pytest.raises(ValueError, match="actions"):
        model(latents, timesteps, actions[:, :-1])
    with pytest.raises(ValueError, match="timesteps"):
        model(latents, timesteps[:, :2], actions)
    with pytest.raises(ValueError, match="latents"):
        model(latents[..., :8], timesteps, actions)
    with pytest.raises(ValueError, match="patch_size"):
        model(latents[:, :, :3, :3], timesteps, actions)
    with pytest.raises(ValueError, match="timesteps: maximum"):
        model(latents, timesteps + 2000.0, actions)
    with pytest.raises(ValueError, match="actions: contains 1 non-finite"):
        model(latents, timesteps, actions.at[0, 2, 1].set(jnp.nan))
    with pytest.raises(ValueError, match="num_heads"):
        WorldModel(dataclasses.replace(CFG, num_heads=3), rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match="freq_dim"):
        dataclasses.replace(CFG, freq_dim=31).validate()
    with pytest.raises(ValueError, match="temporal patch"):
        WorldModel(dataclasses.replace(CFG, patch_size=(2, 2, 2)), rngs=nnx.Rngs(0))


def _count(factory) -> int:
    return sum(int(np.prod(x.shape)) for x in jax.tree.leaves(nnx.split(sharding.abstract_module(factory))[1]))


def test_parameter_counts(shared_dir):
    import json

    with open(os.path.join(shared_dir, "reference", "wan22", "meta.json")) as f:
        meta = json.load(f)["dit"]
    ref_cfg = wan22_dit.config_from_official(meta["config"])
    assert _count(lambda: WanDiT(ref_cfg, rngs=nnx.Rngs(0))) == meta["n_params"]
    full = DiTConfig()
    dit = _count(lambda: WanDiT(full, rngs=nnx.Rngs(0)))
    world = _count(lambda: WorldModel(full, rngs=nnx.Rngs(0)))
    assert 4.9e9 < dit < 5.1e9, f"TI2V-5B DiT has {dit:,} parameters"
    assert 0 < world - dit < 0.01 * dit, f"action branches add {world - dit:,} parameters"


def test_weights_stored_in_the_compute_dtype_give_bit_identical_outputs():
    """sword_jax.precision: a bf16-compute world model with its matmul weights stored in bf16 gives
    the same outputs bit for bit, holds fewer bytes, and keeps the float32 parameters it reads in
    float32 (norms, modulation tables, the patch embedding)."""
    from sword_jax.precision import parameter_bytes, store_in_compute_dtype

    _, state = _randomized(CFG)
    graphdef = _graphdef(dataclasses.replace(CFG, compute_dtype="bfloat16"))
    cast = store_in_compute_dtype(graphdef, state)
    inputs = _inputs(6)
    np.testing.assert_array_equal(apply(graphdef, cast, *inputs), apply(graphdef, state, *inputs))
    dtypes = {jax.tree_util.keystr(path): x.dtype for path, x in jax.tree_util.tree_leaves_with_path(cast)}
    q = next(k for k in dtypes if "self_attn" in k and "'q'" in k and "kernel" in k)
    assert dtypes[q] == jnp.bfloat16
    kept = [k for k in dtypes if "modulation" in k or "patch_kernel" in k or "norm" in k]
    assert kept and all(dtypes[k] == jnp.float32 for k in kept)
    assert parameter_bytes(cast) < 0.7 * parameter_bytes(state)
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(state))  # the input is left alone
    # a float32-compute model has nothing to store differently
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(store_in_compute_dtype(_graphdef(CFG), state)))


def test_bfloat16_residual_stream_is_close_to_float32_and_carried_in_bfloat16():
    """model.residual_dtype=bfloat16: the stream between blocks is bf16 (block outputs), the output
    stays float32 and close to the float32-stream model (both with bf16 compute)."""
    _, state = _randomized(CFG)
    bf16 = dataclasses.replace(CFG, compute_dtype="bfloat16")
    latents, timesteps, actions = _inputs(7)
    ref = apply(_graphdef(bf16), state, latents, timesteps, actions)
    low = _graphdef(dataclasses.replace(bf16, residual_dtype="bfloat16"))
    out = apply(low, state, latents, timesteps, actions)
    assert out.dtype == jnp.float32
    rel = _max_diff(out, ref) / float(jnp.max(jnp.abs(ref)))
    assert 0.0 < rel < 5e-2, rel

    def scan_carries(jaxpr):  # the first carry of every scan, nested jaxprs included
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "scan":
                yield eqn.outvars[0].aval
            for value in eqn.params.values():
                inner = getattr(value, "jaxpr", value)
                if hasattr(inner, "eqns"):
                    yield from scan_carries(inner)

    def stream_dtypes(graphdef):
        closed = jax.make_jaxpr(functools.partial(world_model_apply, graphdef))(state, latents, timesteps, actions)
        return {a.dtype for a in scan_carries(closed.jaxpr) if a.shape[-1] == CFG.dim}

    assert stream_dtypes(low) == {jnp.dtype(jnp.bfloat16)}
    assert stream_dtypes(_graphdef(bf16)) == {jnp.dtype(jnp.float32)}


@pytest.mark.parametrize("cross_attn, adaln, scan", [(True, True, True), (True, True, False), (False, True, True)])
def test_conditioned_forward_equals_the_plain_forward(cross_attn, adaln, scan):
    """Actions conditioned once (cross-attention keys / values per block, AdaLN offset) and applied give the
    plain forward's predictions, with and without the layer scan and with the null context token."""
    cfg = dataclasses.replace(CFG, action_cross_attn=cross_attn, action_adaln=adaln, scan_layers=scan)
    graphdef, state = _randomized(cfg)
    latents, timesteps, actions = _inputs(3, cfg=cfg)
    plain = apply(graphdef, state, latents, timesteps, actions)

    @jax.jit
    def conditioned(state, latents, timesteps, actions):
        model = nnx.merge(graphdef, state)
        return model.apply_conditioned(latents, timesteps, model.condition(actions))

    keys, values = jax.jit(lambda s, a: nnx.merge(graphdef, s).condition(a).context_kv)(state, actions)
    lc = actions.shape[1] if cross_attn else 1
    assert keys.shape == values.shape == (cfg.num_layers, 2, lc, cfg.num_heads, cfg.dim // cfg.num_heads)
    np.testing.assert_allclose(np.asarray(conditioned(state, latents, timesteps, actions)), np.asarray(plain),
                               rtol=1e-5, atol=1e-5)
