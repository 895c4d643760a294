import dataclasses
import re

import pytest

import configs
from configs.cli import ConfigError, flatten


@pytest.mark.parametrize("name", ["sword:tiny", "sword:small", "sword:paper", "cache_ablation:linear-direct-all",
                                  "cache_ablation:wovr", "cache_ablation:small-tf"])
def test_variants_validate(name):
    assert configs.get(name).validate() is not None


def test_paper_shapes():
    cfg = configs.get("sword:paper")
    assert (cfg.model.dim, cfg.model.ffn_dim, cfg.model.num_heads, cfg.model.num_layers) == (3072, 14336, 24, 30)
    assert cfg.vae.z_dim == 48 and cfg.data.image_size == 256
    assert (cfg.data.context_frames, cfg.data.predict_frames) == (4, 8)


def test_cache_ablation_has_eight_designs():
    from configs import cache_ablation

    designs = {configs.get(f"cache_ablation:{d}").cache for d in cache_ablation.DESIGNS}
    assert len(designs) == 8
    assert configs.get("sword:tiny").cache.schedule == "linear"
    assert configs.get("sword:tiny").cache.replacement == "direct"
    assert configs.get("sword:tiny").cache.scope == "all"


def test_dotted_overrides_are_typed():
    cfg, rest = configs.from_argv(["--model.num_layers=4", "--cache.scope", "single", "--model.patch_size=1,2,2",
                                   "--flow.pixel_round_trip=true", "--out", "x"])
    assert cfg.model.num_layers == 4 and cfg.cache.scope == "single"
    assert cfg.model.patch_size == (1, 2, 2) and cfg.flow.pixel_round_trip is True
    assert rest == ["--out", "x"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.model.dim = 3  # type: ignore[misc]


@pytest.mark.parametrize(
    "override, needle",
    [
        ("--model.num_layerz=4", "model.num_layerz"),
        ("--nosection.x=1", "nosection.x"),
        ("--model.num_layers=four", "model.num_layers"),
        ("--cache.schedule=exp", "cache.schedule"),
        ("--rl.sft.stepz=5", "rl.sft.stepz"),
        ("--rl.grpo.group_size=1", "rl.grpo.group_size"),
        ("--rl.grpo.steps=-1", "rl.grpo.steps"),
        ("--rl.grpo.eval_every=0", "rl.grpo.steps must be >= 0 and rollout_batch, eval_every"),
        ("--rl.grpo.learning_rate=0", "rl.grpo.learning_rate"),
        ("--rl.imagined.oversample=0", "rl.imagined.oversample must be >= 1"),
    ],
)
def test_bad_override_names_the_key(override, needle):
    with pytest.raises((ConfigError, ValueError), match=needle.replace(".", r"\.")):
        configs.from_argv([override])


@pytest.mark.parametrize(
    "override, needle",
    [
        ("--data.episode_frames=34", "1+4k"),
        ("--model.num_heads=3", "num_heads"),
        ("--data.image_size=48", "image_size"),
        ("--eval.horizon_frames=30", "horizon_frames"),
        ("--data.policy_rollout_workers=0", "data.policy_rollout_workers must be >= 1"),
    ],
)
def test_impossible_settings_rejected(override, needle):
    with pytest.raises(ValueError, match=re.escape(needle)):
        configs.from_argv([override])


@pytest.mark.parametrize("overrides, match", [
    (["--rl.action_dim=6"], "rl.action_dim"),
    (["--rl.chunk_len=4"], "rl.chunk_len"),
    (["--flow.pixel_round_trip=true", "--data.context_frames=12"], "pixel_round_trip"),
    (["--flow.pixel_round_trip=true", "--data.context_frames=8", "--rl.imagined.execute_steps=4"],
     "rl.imagined.execute_steps"),
    (["--sim.resolution=64"], "sim.resolution"),
])
def test_validate_cross_checks_sections(overrides, match):
    with pytest.raises(ConfigError, match=match):
        configs.from_argv(["--config", "sword:tiny", *overrides])


def test_rl_settings_are_set_in_their_sections():
    cfg, _ = configs.from_argv(["--rl.sft.steps=5", "--rl.grpo.group_size=3", "--rl.env.action_ensemble=false",
                                "--rl.env.execute_steps=4", "--rl.imagined.execute_steps=4", "--rl.policy.width=48",
                                "--rl.chunk_len=8"])
    tiny = configs.get("sword:tiny").rl
    assert (cfg.rl.sft.steps, cfg.rl.grpo.group_size, cfg.rl.policy.width) == (5, 3, 48)
    assert (cfg.rl.env.execute_steps, cfg.rl.env.action_ensemble, cfg.rl.imagined.execute_steps) == (4, False, 4)
    # the rest of each section keeps the variant's values
    assert cfg.rl.sft.batch_size == tiny.sft.batch_size and cfg.rl.grpo.steps == tiny.grpo.steps
    assert cfg.rl.policy.layers == tiny.policy.layers and cfg.rl.imagined.max_chunks == tiny.imagined.max_chunks
    assert flatten(cfg)["rl.sft.steps"] == 5 and "rl.sft_steps" not in flatten(cfg)
    with pytest.raises(ConfigError, match=r"rl\.policy' is a section"):
        configs.from_argv(["--rl.policy=3"])


def test_flat_rl_keys_of_earlier_versions_name_their_new_key():
    from sword_jax.rl.config import RENAMED, RefreshConfig, RLConfig, ValueConfig

    for old, new in RENAMED.items():
        with pytest.raises(ConfigError, match=f"^{re.escape(f'rl.{old} is now rl.{new}')}$"):
            configs.from_argv([f"--rl.{old}=1"])
    # every new key exists, and every RL key is one of them, kept its name at the top of rl, or came after the split
    added_after_the_split = {"imagined.keyframe_fraction", "grpo.eval_sampled", "imagined.eval_replay_settle_steps",
                             "imagined.success_frames", "imagined.sim_microbatches", "grpo.minibatches",
                             "grpo.max_sample_rounds", "grpo.min_mixed_fraction", "grpo.min_mixed_groups",
                             "env.backend", "imagined.shared_group_noise", "imagined.guard_margin",
                             "imagined.guard_min_failures", "imagined.confirm_success", "imagined.sim_precision",
                             "imagined.decoder", "sft.init", "reward_model.image_size", "imagined.oversample",
                             "imagined.guard_on", "imagined.reward", "imagined.fidelity_trajectories", "sft.image_aug",
                             "sft.decoded_fraction", "sft.decoded_source", "sft.decoded_window", "grpo.scale_by_std",
                             "grpo.shuffle_returns", "imagined.calibrate_steps", "imagined.keyframe_from",
                             "imagined.start_encoding",
                             *(f"refresh.{f.name}" for f in dataclasses.fields(RefreshConfig)),
                             *(f"value.{f.name}" for f in dataclasses.fields(ValueConfig))}
    leaves = {key[len("rl."):] for key in flatten(configs.get("sword:tiny")) if key.startswith("rl.")}
    assert set(RENAMED.values()) <= leaves and added_after_the_split <= leaves
    assert leaves - set(RENAMED.values()) - added_after_the_split == {
        f.name for f in dataclasses.fields(RLConfig) if not dataclasses.is_dataclass(f.default)}


@pytest.mark.parametrize("variant", ["tiny", "small", "paper"])
def test_rl_configs_saved_flat_by_earlier_versions_load_into_their_sections(variant):
    """Policy and reward-model checkpoints store the RL config; one saved before the split still loads."""
    import json
    import operator

    from sword_jax.load import section_from_dict
    from sword_jax.rl.config import RENAMED, RLConfig

    rl = configs.get(f"sword:{variant}").rl
    kept = {f.name: getattr(rl, f.name) for f in dataclasses.fields(rl) if not dataclasses.is_dataclass(f.default)}
    flat = {**kept, **{old: operator.attrgetter(new)(rl) for old, new in RENAMED.items()}}
    assert section_from_dict(RLConfig, json.loads(json.dumps(flat))) == rl
    assert section_from_dict(RLConfig, json.loads(json.dumps(dataclasses.asdict(rl)))) == rl


def test_augment_settings_no_pipeline_reads_are_gone():
    cfg, _ = configs.from_argv(["--config", "sword:tiny", "--augment.fov_deg=60"])
    assert cfg.augment.fov_deg == 60.0
    for removed in ("mode", "raw_fraction"):
        with pytest.raises(ConfigError):
            configs.from_argv(["--config", "sword:tiny", f"--augment.{removed}=0.5"])


def test_eval_metrics_are_configurable_and_checked():
    import dataclasses

    import pytest

    from sword_jax.metrics.config import EvalConfig

    small = configs_get("small")
    assert "fid" not in small.eval.metrics and {"lpips", "fvd", "flolpips"} <= set(small.eval.metrics)
    for bad in ((), ("lpips", "kid"), ("lpips", "lpips")):
        with pytest.raises(ValueError, match="eval.metrics"):
            dataclasses.replace(EvalConfig(), metrics=bad).validate()


def configs_get(variant):
    from configs import sword

    return sword.get(variant)


def test_vae_geometry_is_read_from_the_vae_config():
    """Frames per latent and the spatial stride come from ``VAEConfig`` wherever a config is at hand."""
    from sword_jax.api import WorldModelSpec
    from sword_jax.pipeline.world_model import latent_grid
    from sim.world_model_eval import effective_horizon

    cfg = configs.get("sword:tiny")
    assert (cfg.vae.temporal_factor, cfg.vae.spatial_factor) == (4, 16)
    # a VAE that halves time once and space three times (x2 patchify, two x2 levels)
    vae = dataclasses.replace(cfg.vae, dim_mult=(1, 2, 2), temporal_downsample=(False, True))
    assert (vae.temporal_factor, vae.spatial_factor) == (2, 8)
    odd = dataclasses.replace(cfg, vae=vae)
    side = cfg.data.image_size // 8
    assert latent_grid(odd) == (1 + (cfg.data.episode_frames - 1) // 2, side, side, vae.z_dim)
    k, p = cfg.data.context_frames // 2, cfg.data.predict_frames // 2
    n = (cfg.eval.horizon_frames - 1 - 2 * k) // (2 * p)
    assert effective_horizon(odd, 10_000) == (1 + 2 * k + 2 * p * n, k, p)
    # the action DiT groups 4 actions per latent frame: an experiment with this VAE is refused, naming it
    with pytest.raises(ValueError, match=r"vae.temporal_downsample=\(False, True\) compresses time by 2"):
        odd.validate()
    spec = WorldModelSpec(model=cfg.model, flow=cfg.flow, vae=vae, image_size=64, num_context=1, num_future=2)
    assert (spec.given_frames, spec.frames_per_chunk, spec.latent_size, spec.num_actions(3)) == (3, 4, 8, 15)
