"""The light decoder in the learned simulator and the pipeline: the builder decodes GRPO's frames with it at its
own (the policy's) resolution and a rollout runs; GRPO's setup loads it when ``rl.imagined.decoder=light``; the
pipeline's ``light_decoder`` stage trains it only then and hands its path to GRPO; the entry point trains one
that loads back, and resumes exactly."""

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import configs
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, PolicyConfig, RLConfig
from sword_jax.rl.learned_simulator import StartState, toy_reward_model
from sword_jax.rl.policy import VLAPolicy, tokenize_instructions
from sword_jax.rl.rollout import imagined_rollout
from sword_jax.rl.sim_builder import build_simulator, inference_light_decoder
from sword_jax.vae import api as vae_api
from sword_jax.vae import light_decoder as light
from sword_jax.vae.config import LightDecoderConfig
from tests.support.light_decoder import numpy_weights

POLICY_SIZE = 16  # the tiny VAE's 2x2 latents of 32 px frames, decoded at 16 px


def _tiny_models(vae_weights=False):
    """The tiny world model (zero weights: its predictions are faked here) and VAE (random weights, or zeros when a
    light decoder's simulator reads only its geometry)."""
    from sword_jax.dit.action_dit import WorldModel

    cfg = configs.get("sword:tiny")
    world_model = numpy_weights(lambda: WorldModel(dataclasses.replace(cfg.model, num_layers=1), rngs=nnx.Rngs(0)),
                                zeros=True)
    vae = numpy_weights(lambda: vae_api.create_vae(cfg.vae, key=jax.random.key(1)), seed=1, zeros=not vae_weights)
    return cfg, world_model, vae


def _light(seed=0):
    return numpy_weights(lambda: light.LightDecoder(LightDecoderConfig(width=16, blocks=1), z_dim=48, scale=8,
                                                    temporal_factor=4, rngs=nnx.Rngs(seed)), seed=seed)


def _fake_world_model(monkeypatch):
    """Predictions that are a fixed function of the chunk's actions (the DiT's compile is not what is tested)."""
    from sword_jax.rl import world_model_sim

    base = jax.random.normal(jax.random.key(9), (1, 2, 2, 2, 48))

    def predict(model_fn, first, context, actions, *, key, num_future, cfg, num_steps):
        return base[:, :num_future] + jnp.mean(actions[:, -num_future:, :1]) + 0.1 * context[:, -1:]

    monkeypatch.setattr(world_model_sim, "predict_chunk", predict)
    return base


def test_the_builder_decodes_with_the_light_decoder_at_the_policy_resolution_and_a_rollout_runs(monkeypatch):
    cfg, (wm_graphdef, wm_state), (vae_graphdef, vae_state) = _tiny_models()
    base = _fake_world_model(monkeypatch)
    light_graphdef, light_state = _light()
    sims = {precision: build_simulator(wm_graphdef, wm_state, vae_graphdef, vae_state, precision=precision,
                                       light_decoder=(light_graphdef, light_state), flow_cfg=cfg.flow, frame_size=32,
                                       sample_steps=1)
            for precision in ("float32", "fast")}
    assert {s.frame_size for s in sims.values()} == {POLICY_SIZE} and sims["fast"].max_slice >= 64
    # its weights hold no VAE encoder: no round trip of real frames (GRPO's closed loop logs no VAE share)
    assert all(s.round_trip_fn is None for s in sims.values())
    assert light.attributes(*inference_light_decoder(light_graphdef, light_state, "fast"))[3] == "bfloat16"
    start_latents = jax.random.normal(jax.random.key(3), (2, 2, 2, 48))
    start = StartState(jnp.zeros((32, 32, 3)), jnp.zeros(8), jnp.zeros(8, jnp.int32), start_latents)

    @jax.jit
    def first_chunk(sim):  # the simulator's frames, and the light decoder's whole stream of [start, predicted]
        frames = sim.step(sim.init(start), jnp.zeros((8, 7)), key=jax.random.key(0))[1]
        future = base + 0.1 * start_latents[None, 1:]
        whole = light.decode(light_graphdef, light_state, jnp.concatenate([start_latents[None], future], axis=1))
        return frames, jnp.clip((whole[0, -8:] + 1.0) * 0.5, 0.0, 1.0)

    frames, expected = first_chunk(sims["float32"])
    assert frames.shape == (8, POLICY_SIZE, POLICY_SIZE, 3)
    np.testing.assert_allclose(np.asarray(frames), np.asarray(expected), atol=1e-5)

    # a rollout from start frames at the VAE's 32 px: the policy and the detector read 16 px frames throughout
    rl = RLConfig(image_size=POLICY_SIZE, action_bins=8, success_threshold=1.0,
                  policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32),
                  grpo=GRPOConfig(group_size=2), imagined=ImaginedConfig(max_chunks=2))
    graphdef, params = numpy_weights(lambda: VLAPolicy(rl, rngs=nnx.Rngs(0)))
    tokens = jnp.asarray(tokenize_instructions(["pick up the bowl", "open the drawer"], 32))
    starts = StartState(jax.random.uniform(jax.random.key(4), (2, 32, 32, 3)), jnp.zeros((2, 8)), tokens,
                        jnp.stack([start_latents, -start_latents]))
    rollout = jax.jit(lambda p, s: imagined_rollout(graphdef, p, s, toy_reward_model(), starts, rl,
                                                    key=jax.random.key(0), record_frames=True, group_size=2))(
        params, sims["fast"])
    assert rollout.frames.shape == (4, 2, 8, POLICY_SIZE, POLICY_SIZE, 3)
    assert rollout.obs_frames.shape == (4, 2, POLICY_SIZE, POLICY_SIZE, 3)
    assert np.all(np.isfinite(np.asarray(rollout.frames))) and np.isfinite(np.asarray(rollout.log_probs)).all()
    # the second decision sees the first chunk's last frame
    np.testing.assert_array_equal(np.asarray(rollout.obs_frames[:, 1]), np.asarray(rollout.frames[:, 0, -1]))


def test_grpo_setup_decodes_with_the_light_decoder_only_when_configured(tmp_path, monkeypatch):
    from sword_jax import load
    from sword_jax.pipeline.grpo import GRPOInputs, world_model_setup
    from sword_jax.pipeline.light_decoder import save_light_decoder
    from sword_jax.rl.grpo_loop import grpo_run_id
    from sword_jax.rl.params_io import save_params
    from sword_jax.rl.reward_model import build_detector

    _, world_model, vae = _tiny_models(vae_weights=True)
    monkeypatch.setattr(load, "experiment_world_model", lambda cfg, path: world_model)
    monkeypatch.setattr(load, "experiment_vae", lambda cfg, path, mesh=None: vae)
    flags = ["--config", "sword:tiny", "--model.num_layers=1", f"--rl.image_size={POLICY_SIZE}",
             "--rl.imagined.eval_replay_episodes=0"]
    full = configs.from_argv(flags)[0]
    lit = configs.from_argv(flags + ["--rl.imagined.decoder=light"])[0]
    reward = str(tmp_path / "detector")
    save_params(reward, build_detector(lit.rl, seed=0)[1], lit.rl, kind="reward_model", step=0)
    light_path = str(tmp_path / "light_decoder")
    save_light_decoder(light_path, _light()[1], lit)
    graphdef, state, meta = load.load_light_decoder(light_path)
    assert (meta["scale"], meta["frame_size"], meta["latent_size"]) == (8, POLICY_SIZE, 2)
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(_light()[1])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    inputs = GRPOInputs(world_model="wm", vae="vae", reward=reward)
    with pytest.raises(ValueError, match="needs the light decoder"):
        world_model_setup(lit, lit.rl, inputs, None)
    light_sim = world_model_setup(lit, lit.rl, dataclasses.replace(inputs, light_decoder=light_path), None).sim
    full_sim = world_model_setup(full, full.rl, inputs, None).sim
    assert (light_sim.frame_size, full_sim.frame_size) == (POLICY_SIZE, 32)
    assert jax.tree.structure(light_sim.params[1]) == jax.tree.structure(state)
    # a GRPO checkpoint records the decoder only when it is not the default (older runs still resume)
    assert grpo_run_id(lit.rl, seed=0, simulator="world_model")["rl.imagined.decoder"] == "light"
    assert "rl.imagined.decoder" not in grpo_run_id(full.rl, seed=0, simulator="world_model")


def test_the_light_decoder_stage_runs_only_when_enabled_and_its_path_reaches_grpo(tmp_path, monkeypatch):
    from sim import grpo_training, pipeline_stages, policy_stages
    from sword_jax.pipeline import light_decoder, report
    from sword_jax.pipeline.grpo import GRPOInputs
    from sword_jax.pipeline.stages import Context

    names = [s.name for s in pipeline_stages.STAGES]
    assert names.index("vae") < names.index("latents") < names.index("light_decoder") < names.index("policy")
    needs = {s.name: s.needs for s in pipeline_stages.STAGES}
    assert needs["light_decoder"] == ("vae", "latents") and "light_decoder" in needs["policy"]
    calls = []
    trained = {"path": str(tmp_path / "ld" / "checkpoints"), "steps": 2, "frame_size": 32, "params": 10,
               "eval": {"init_l1": 0.3, "final_l1": 0.2, "init_psnr": 15.0, "final_psnr": 17.5},
               "strip": str(tmp_path / "ld" / "strip.png")}
    monkeypatch.setattr(light_decoder, "run_light_decoder", lambda cfg, **kw: calls.append((cfg, kw)) or dict(trained))
    monkeypatch.setattr(grpo_training, "run_grpo",
                        lambda cfg, inputs, **kw: calls.append(inputs) or {"curve": [], "workdir": "grpo_dir"})
    results = {"data": {"train": {"path": "train.hdf5"}, "demos": {"path": "demos.hdf5"}}, "vae": {"path": "vae_dir"},
               "latents": {"path": "latents.npz"}, "world_model": {"workdir": "wm_dir"}, "sft_policy": {"path": "sft"},
               "reward_model": {"path": "rm_dir"}}
    stage_results = {}
    for decoder in ("full", "light"):
        cfg = configs.from_argv(["--config", "sword:tiny", f"--workdir={tmp_path}",
                                 f"--rl.imagined.decoder={decoder}"])[0]
        ctx = Context(cfg=cfg, workdir=str(tmp_path), results=dict(results))
        ctx.results["light_decoder"] = stage_results[decoder] = pipeline_stages.stage_light_decoder(ctx)
        policy_stages.grpo_in_world_model(ctx)
        report.write(ctx)  # the report tells what the light decoder reached, when one was trained
        text = open(os.path.join(str(tmp_path), "report.md")).read()
        assert ("## Light rollout decoder" in text) == (decoder == "light")
        assert decoder == "full" or "0.3 -> 0.2, PSNR 15 -> 17.5 dB" in text
    assert stage_results["full"] == {"path": "", "skipped": "rl.imagined.decoder=full"}
    grpo_full, (ld_cfg, ld_kwargs), grpo_light = calls
    assert grpo_full == GRPOInputs(demos=("demos.hdf5",), world_model="wm_dir", vae="vae_dir", policy="sft",
                                   reward="rm_dir", light_decoder="")
    assert ld_cfg.workdir == str(tmp_path / "light_decoder") and os.path.isdir(ld_cfg.workdir)
    assert ld_kwargs == {"vae": "vae_dir", "latents": "latents.npz"}
    assert grpo_light.light_decoder == str(tmp_path / "ld" / "checkpoints")


def _vae_and_latents(tmp_path):
    """The tiny VAE saved as train_vae saves it, a latents.npz of 3 episodes of 5 latents, and the entry point's
    flags for them."""
    from sim.vae_training import save_vae

    _, _, (vae_graphdef, vae_state) = _tiny_models(vae_weights=True)
    params, rest = vae_state.split(nnx.Param, ...)
    save_vae(str(tmp_path / "vae"), vae_graphdef, params, rest)
    latents = np.asarray(jax.random.normal(jax.random.key(0), (3, 5, 2, 2, 48)))
    np.savez(tmp_path / "latents.npz", latents=latents, actions=np.zeros((3, 17, 7), np.float32))
    return ["--config", "sword:tiny", "--vae", str(tmp_path / "vae"), "--latents", str(tmp_path / "latents.npz"),
            "--mesh.data=2", "--mesh.tensor=4", "--light_decoder.clip_latents=2", "--trainer.log_every=1",
            f"--rl.image_size={POLICY_SIZE}"]


@pytest.mark.slow  # test_light_decoder's distillation and resume test trains one in the default run
def test_train_light_decoder_writes_a_decoder_that_loads_back_and_decodes_at_its_size(tmp_path):
    """The entry point's smoke run: one step on the tiny config; the weights load back with their geometry, the
    held clips' L1 to the teacher fell, the strip is written."""
    from sword_jax.load import load_light_decoder
    from train import train_light_decoder

    summary = train_light_decoder.main(_vae_and_latents(tmp_path) + [
        "--workdir", str(tmp_path / "run"), "--light_decoder.train_steps=1"])
    assert summary["frame_size"] == POLICY_SIZE and summary["latent_size"] == 2 and summary["steps"] == 1
    assert os.path.exists(summary["strip"]) and summary["eval"]["final_l1"] < summary["eval"]["init_l1"]
    assert [r["step"] for r in _rows(str(tmp_path / "run"))] == [1]
    graphdef, state, meta = load_light_decoder(summary["path"])
    assert (meta["frame_size"], meta["scale"]) == (POLICY_SIZE, 8)
    assert light.decode(graphdef, state, jnp.zeros((1, 2, 2, 2, 48))).shape == (1, 5, POLICY_SIZE, POLICY_SIZE, 3)


def _rows(workdir):
    rows = [json.loads(line) for line in open(os.path.join(workdir, "metrics.jsonl"))]
    return [{k: v for k, v in row.items() if k not in ("elapsed_s", "eta_s")} for row in rows]


@pytest.mark.slow  # three runs of the entry point, each compiling the sharded distillation step (~1 min on 2 cores)
def test_train_light_decoder_resumed_equals_uninterrupted(tmp_path):
    """Stopped after a step and run again, the entry point ends bit-identical to an uninterrupted run: weights,
    metrics.jsonl and the held clips' numbers."""
    from sword_jax.load import load_light_decoder
    from train import train_light_decoder

    args = _vae_and_latents(tmp_path) + ["--trainer.checkpoint_every=1"]
    straight, split = str(tmp_path / "straight"), str(tmp_path / "split")
    summary = train_light_decoder.main(args + ["--workdir", straight, "--light_decoder.train_steps=3"])
    train_light_decoder.main(args + ["--workdir", split, "--light_decoder.train_steps=1"])
    resumed = train_light_decoder.main(args + ["--workdir", split, "--light_decoder.train_steps=3"])
    for a, b in zip(jax.tree.leaves(load_light_decoder(summary["path"])[1]),
                    jax.tree.leaves(load_light_decoder(resumed["path"])[1])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert _rows(split) == _rows(straight) and [r["step"] for r in _rows(split)] == [1, 2, 3]
    assert resumed["eval"] == summary["eval"]
