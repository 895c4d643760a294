"""benchmarks.bench_closed_loop on the toy world: a simulator equal to the environment leaves no closed-loop error
and its detector agrees with reality on every trajectory, a noisy one drifts, variants are paired trajectory by
trajectory, the real row runs the policy on the environment's own frames; bad command lines are refused by name."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import configs
from benchmarks import bench_closed_loop as bench
from sword_jax import cli
from sword_jax.rl.config import GRPOConfig, ImaginedConfig, PolicyConfig, RLConfig
from sword_jax.rl.learned_simulator import (ToyState, instruction_target, toy_render, toy_reward_model, toy_simulator,
                                            toy_start_states)
from sword_jax.rl.policy import build_policy, tokenize_instructions

CFG = RLConfig(image_size=8, action_bins=8, proprio_dim=4,
               policy=PolicyConfig(width=16, heads=2, layers=1, max_instruction_bytes=32, proprio_encoding="raw"),
               grpo=GRPOConfig(group_size=4, temperature=1.0),
               imagined=ImaginedConfig(max_chunks=4, fidelity_trajectories=8))
TEXTS = ["pick up the black bowl on the plate", "put the bowl on the stove", "open the drawer"]
STEP = 0.08  # the toy simulator's default step, which the environment below moves by


class ToyEnv:
    """The toy world as a real environment (starts ``[position xy, target xy]``), with the proprio the toy
    simulator reports (the position, padded): success when the toy detector's score passes the threshold."""

    def __init__(self, threshold):
        self.rm, self.threshold = toy_reward_model(), threshold

    def _obs(self, pos, target):
        frames = jax.vmap(lambda p, t: toy_render(ToyState(p, t), 8))(pos, target)
        proprio = jnp.concatenate([pos, jnp.zeros((pos.shape[0], CFG.proprio_dim - 2), jnp.float32)], axis=1)
        return {"frames": frames, "proprio": proprio}

    def reset(self, starts):
        starts = jnp.asarray(starts, jnp.float32)
        state = (starts[:, :2], starts[:, 2:])
        return state, self._obs(*state)

    def step(self, state, actions):
        pos, target = state
        pos = jnp.clip(pos + STEP * jnp.clip(actions[:, :2], -1.0, 1.0), -1.0, 1.0)
        obs = self._obs(pos, target)
        return (pos, target), obs, self.rm.score(obs["frames"]) >= self.threshold


def _batches(n=2):
    """``n`` batches of the three instructions' toy starts, one of them placed near its target."""
    tokens = jnp.asarray(tokenize_instructions(TEXTS, 32))
    out = []
    for i in range(n):
        start = toy_start_states(tokens, key=jax.random.key(10 + i), frame_size=8, proprio_dim=CFG.proprio_dim)
        targets = jax.vmap(instruction_target)(tokens)
        near = targets[1] + jnp.asarray([0.1, 0.0])
        start = start._replace(proprio=start.proprio.at[1, :2].set(near),
                               frame=start.frame.at[1].set(toy_render(ToyState(near, targets[1]), 8)))
        out.append((start, jnp.concatenate([start.proprio[:, :2], targets], axis=1)))
    return out


def _measure(simulators, real=True, rl=CFG, read_state=None, **kwargs):
    graphdef, params = build_policy(rl, seed=0)
    env = ToyEnv(rl.success_threshold)
    detector = toy_reward_model()
    real_fn = bench.make_real(graphdef, rl, env, max_steps=rl.imagined.max_chunks * rl.imagined_actions_per_decision)
    keys = [jax.random.key(3), jax.random.key(4)]
    return bench.measure_variants(graphdef, params, rl, {n: (s, detector) for n, s in simulators.items()}, _batches(),
                                  keys, env=env, real_fn=real_fn if real else None, log=lambda _: None,
                                  read_state=read_state, **kwargs)


def test_a_faithful_simulator_leaves_no_gap_and_a_noisy_one_drifts():
    faithful = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim)
    noisy = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim, noise=0.08)
    out = _measure({"faithful": faithful, "again": faithful, "noisy": noisy})
    rows = {r["name"]: r for r in out["variants"]}
    n = 2 * len(TEXTS) * CFG.grpo.group_size
    assert [r["name"] for r in out["variants"]] == ["faithful", "again", "noisy"]
    a, b = rows["faithful"], rows["noisy"]
    assert a["paid"]["of"] == b["paid"]["of"] == out["real"]["paid"]["of"] == n
    assert 0 < a["paid"]["successes"] < n, "the designed starts give both outcomes"
    # equal to the environment: no closed-loop error at any decision, and the detector is reality
    assert [d["decision"] for d in a["decisions"]] == list(range(1, CFG.imagined.max_chunks))
    for d in a["decisions"]:
        assert d["frame_error"] == pytest.approx(0.0, abs=1e-5) and d["action_gap"] == pytest.approx(0.0, abs=1e-6)
        assert d["sharpness"] == pytest.approx(1.0, rel=1e-4)  # as sharp as the real frames
    assert a["detector"]["successes"] == a["paid"]["successes"] and a["precision"]["rate"] == 1.0
    # the same simulator again: the same trajectories, paired to a difference of exactly 0
    assert rows["again"]["vs_first"]["difference"] == 0.0 and rows["again"]["paid"] == a["paid"]
    assert "vs_first" not in a
    # jitter in the motion: the imagined frames leave the real ones, more so decision after decision
    errors = [d["frame_error"] for d in b["decisions"]]
    assert errors[0] > 1e-3 and errors[-1] > errors[0], errors
    low, high = b["vs_first"]["ci95"]
    assert low <= b["vs_first"]["difference"] <= high
    assert "frame_error_vae" not in b["decisions"][0]  # the toy simulator has no decoder round trip
    assert "sharpness_vae" not in b["decisions"][0] and "sharpness" in bench.line(a)
    assert 0.0 <= out["real"]["paid"]["rate"] <= 1.0 and "decisions" not in out["real"]


def test_without_observed_trajectories_only_what_reality_paid():
    import dataclasses

    rl = dataclasses.replace(CFG, imagined=dataclasses.replace(CFG.imagined, fidelity_trajectories=0))
    faithful = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim)
    out = _measure({"faithful": faithful}, real=False, rl=rl)
    (row,) = out["variants"]
    assert row["decisions"] == [] and "real" not in out
    assert row["detector"]["successes"] == row["paid"]["successes"]


def test_variants_and_pipeline_are_refused_by_name(tmp_path):
    cfg = configs.get("sword:tiny")
    assert bench.parse_variants(["n1=flow.noise_scale=1", "n0=flow.noise_scale=0,flow.sample_steps=8"], cfg) == {
        "n1": ("flow.noise_scale=1",), "n0": ("flow.noise_scale=0", "flow.sample_steps=8")}
    assert bench.parse_variants(["u=flow.sample_shift=1"], cfg) == {"u": ("flow.sample_shift=1",)}
    assert bench.parse_variants(["w=rl.imagined.start_encoding=window", "p=rl.imagined.start_encoding=prefix"],
                                cfg) == {"w": ("rl.imagined.start_encoding=window",),
                                         "p": ("rl.imagined.start_encoding=prefix",)}
    for specs, what in ((["N1=flow.noise_scale=1"], "NAME"), (["a=rl.grpo.steps=3"], "flow.KEY=VALUE"),
                        (["a=rl.imagined.start_encoding=whole"], "start_encoding"),
                        (["a=flow.noise_scale=7"], "flow.noise_scale"), (["a=flow.nothing=1"], "--variant a"),
                        (["a=flow.sample_shift=-1"], "flow.sample_shift"),
                        (["a=flow.noise_scale=1", "a=flow.noise_scale=0"], "twice"),
                        (["real=flow.noise_scale=1"], "reserved"), ([], "at least one")):
        with pytest.raises(cli.UsageError, match=what):
            bench.parse_variants(specs, cfg)
    (tmp_path / "world_model").mkdir()
    with pytest.raises(cli.UsageError, match="vae_run"):
        bench.pipeline_inputs(str(tmp_path))


def test_main_refuses_bad_command_lines(tmp_path):
    policy = tmp_path / "p.npz"
    np.savez(policy, x=np.zeros(1))
    base = ["--config", "sword:tiny", "--pipeline", str(tmp_path), "--policy", str(policy), "--out", str(tmp_path / "o")]
    with pytest.raises(cli.UsageError, match="--batches"):
        bench.main(base + ["--variant", "a=flow.noise_scale=1", "--batches", "0"])
    with pytest.raises(cli.UsageError, match="--frames"):
        bench.main(base + ["--variant", "a=flow.noise_scale=1", "--frames", "-1"])
    with pytest.raises(cli.UsageError, match="at least one"):
        bench.main(base)
    with pytest.raises(cli.UsageError, match="lacks"):
        bench.main(base + ["--variant", "a=flow.noise_scale=1"])
    with pytest.raises(cli.UsageError, match="no such file"):
        bench.main(base[:4] + ["--policy", str(tmp_path / "missing.npz"), "--out", "o", "--variant", "a=flow.noise_scale=1"])
    with pytest.raises(cli.UsageError, match="reckoned"):
        bench.main(base + ["--variant", "a=flow.noise_scale=1", "--rl.imagined.proprio=reckoned"])


def test_a_saved_run_is_recorded_with_its_false_successes_and_without_touching_other_entries(tmp_path, monkeypatch):
    import json

    from benchmarks import common

    faithful = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim)
    noisy = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim, noise=0.08)
    out = dict(_measure({"faithful": faithful, "noisy": noisy}), device="cpu", command="python -m ...", seed=0)
    saved = tmp_path / "closed_loop.json"
    saved.write_text(json.dumps(out))
    latest = tmp_path / "latest.json"
    latest.write_text(json.dumps({"other": {"value": 1}}))
    monkeypatch.setattr(common, "RESULTS", str(latest))
    with pytest.raises(cli.UsageError, match="no date"):  # a file written before the benchmark stamped its date
        bench.main(["--config", "sword:tiny", "--from", str(saved), "--record"])
    assert json.loads(latest.read_text()) == {"other": {"value": 1}}, "a refused record leaves latest.json as it was"
    bench.main(["--config", "sword:tiny", "--from", str(saved), "--record", "--date", "2026-12-02"])
    written = json.loads(latest.read_text())
    entry = written[bench.RECORD_KEY]
    assert written["other"] == {"value": 1} and entry["date"] == "2026-12-02" and entry["data"] == str(saved)
    rows = {r["name"]: r for r in out["variants"]}
    a, b = entry["settings"]["faithful"], entry["settings"]["noisy"]
    assert entry["value"] == a["frame_error"][1] == rows["faithful"]["decisions"][-1]["frame_error"]
    assert a["false_success_share"] == 0.0 and "vs_first" not in a and b["vs_first"] == rows["noisy"]["vs_first"]
    said, paid = rows["noisy"]["detector"]["successes"], rows["noisy"]["paid"]
    true = rows["noisy"]["precision"]["successes"] if rows["noisy"]["precision"] else 0
    assert b["false_success_share"] == pytest.approx((said - true) / (paid["of"] - paid["successes"]))
    assert entry["real"] == out["real"]["paid"]["rate"] and b["decisions"] == [1, CFG.imagined.max_chunks - 1]


def test_recording_a_saved_run_refuses_what_would_measure_and_bad_dates(tmp_path):
    import json

    saved = tmp_path / "closed_loop.json"
    saved.write_text(json.dumps({"variants": [], "date": "2026-12-02"}))
    base = ["--config", "sword:tiny", "--from", str(saved)]
    with pytest.raises(cli.UsageError, match="--pipeline"):
        bench.main(base + ["--pipeline", str(tmp_path)])
    with pytest.raises(cli.UsageError, match="--frames"):
        bench.main(base + ["--frames", "2"])
    with pytest.raises(cli.UsageError, match="YYYY-MM-DD"):
        bench.main(base + ["--date", "2 December"])
    with pytest.raises(cli.UsageError, match="measured on 2026-12-02"):
        bench.main(base + ["--date", "2026-12-01"])
    with pytest.raises(cli.UsageError, match="no measured setting"):
        bench.main(base)
    with pytest.raises(cli.UsageError, match="--from"):
        bench.main(["--config", "sword:tiny", "--from", str(tmp_path / "missing.json")])
    with pytest.raises(cli.UsageError, match="a figure of `small`; this run is sword-tiny"):
        bench.main(["--config", "sword:tiny", "--pipeline", str(tmp_path), "--policy", str(saved), "--out", "o",
                    "--record", "--variant", "a=flow.noise_scale=1"])
    with pytest.raises(cli.UsageError, match="--pipeline, --policy, --out required"):
        bench.main(["--config", "sword:tiny", "--variant", "a=flow.noise_scale=1"])


def test_another_world_model_is_measured_with_the_pipelines_vae_detector_and_demonstrations(tmp_path):
    pipeline = tmp_path / "a"
    for folder in ("world_model", "vae_run/vae", "rl/reward_model", "data"):
        (pipeline / folder).mkdir(parents=True)
    (pipeline / "data" / "demos.hdf5").write_bytes(b"")
    own = bench.pipeline_inputs(str(pipeline))
    assert own["world_model"] == str(pipeline / "world_model")
    (tmp_path / "b" / "world_model").mkdir(parents=True)  # a second pipeline work dir (--adopt): its world model
    for given in (tmp_path / "b", tmp_path / "b" / "world_model"):
        paths = bench.pipeline_inputs(str(pipeline), str(given))
        assert paths == dict(own, world_model=str(tmp_path / "b" / "world_model"))
    with pytest.raises(cli.UsageError, match="lacks .*missing"):
        bench.pipeline_inputs(str(pipeline), str(tmp_path / "missing"))
    saved = tmp_path / "closed_loop.json"
    saved.write_text('{"variants": [], "date": "2026-12-02"}')
    with pytest.raises(cli.UsageError, match="--world-model"):
        bench.main(["--config", "sword:tiny", "--from", str(saved), "--world-model", str(tmp_path / "b")])


def test_a_state_probe_says_where_the_arm_and_the_bowl_of_the_imagined_scene_are(tmp_path):
    """Per decision the probe's readouts of the simulator's frame against the real frame's: none in a faithful
    simulator, some in a noisy one; a probe file train.train_probe writes is read into such a reader, a broken
    one is refused by name."""
    from sword_jax.evaluation import probe

    def mean_colour(frames):  # a designed probe: the arm is the mean colour, the bowl twice it, the gripper open
        mean = jnp.mean(frames, axis=(1, 2))
        return jnp.concatenate([mean, jnp.full_like(mean[:, :1], 0.08), 2.0 * mean], axis=1)

    faithful = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim)
    noisy = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim, noise=0.08)
    rows = {r["name"]: r for r in _measure({"faithful": faithful, "noisy": noisy}, real=False,
                                           read_state=mean_colour)["variants"]}
    for d in rows["faithful"]["decisions"]:
        assert d["ee_cm"] == pytest.approx(0.0, abs=1e-3) and d["bowl_cm"] == pytest.approx(0.0, abs=1e-3)
        assert d["gripper_agree"] == 1.0 and d["ee_motion_cm"] > 0
    noisy_ee = [d["ee_cm"] for d in rows["noisy"]["decisions"]]
    assert min(noisy_ee) > 0.01, noisy_ee  # the noise averages out in a mean colour, not to 0
    assert [d["bowl_cm"] for d in rows["noisy"]["decisions"]] == pytest.approx([2 * e for e in noisy_ee], rel=1e-4)
    assert "ee_cm" not in _measure({"faithful": faithful}, real=False)["variants"][0]["decisions"][0]
    cfg = probe.ProbeConfig(image_size=8, width=4)
    graphdef, params, stats = probe.build_probe(cfg, np.zeros(7), np.ones(7))
    path = probe.save_probe(str(tmp_path / "probe.npz"), params, stats, cfg)
    read, closed_below = bench.probe_reader(path)
    assert read(jnp.zeros((3, 16, 16, 3))).shape == (3, 7) and closed_below == cfg.gripper_closed_below
    (tmp_path / "broken.npz").write_bytes(b"not a probe")
    with pytest.raises(cli.UsageError, match="--probe .*broken.npz"):
        bench.probe_reader(str(tmp_path / "broken.npz"))


def test_variants_may_each_bring_their_own_start_states():
    """Batches given per variant (the same keyframes encoded each variant's way) are each variant's; given the
    same batches under each name the rows are those of the shared batches."""
    graphdef, params = build_policy(CFG, seed=0)
    faithful = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim)
    env, detector, keys = ToyEnv(CFG.success_threshold), toy_reward_model(), [jax.random.key(3), jax.random.key(4)]
    sims = {"a": (faithful, detector), "b": (faithful, detector)}
    shared = bench.measure_variants(graphdef, params, CFG, sims, _batches(), keys, env=env, log=lambda _: None)
    own = bench.measure_variants(graphdef, params, CFG, sims, {"a": _batches(), "b": _batches()}, keys, env=env,
                                 log=lambda _: None)
    for x, y in zip(shared["variants"], own["variants"]):
        assert x["paid"] == y["paid"] and x["decisions"] == y["decisions"]
    other = bench.measure_variants(graphdef, params, CFG, sims, {"a": _batches(), "b": _batches(3)[1:]}, keys, env=env,
                                   log=lambda _: None)
    assert other["variants"][0]["decisions"] == shared["variants"][0]["decisions"]
    assert other["variants"][1]["decisions"] != shared["variants"][1]["decisions"], "b measured its own starts"


def test_the_start_context_error_is_relative_and_zero_for_the_exact_encoding():
    from sword_jax.rl.learned_simulator import StartState

    def start(context):
        latents = jnp.stack([jnp.ones((2, 2, 1)), jnp.asarray(context, jnp.float32)])[None]  # [1, 1 + k, h, w, z]
        return StartState(jnp.zeros((8, 8, 3)), jnp.zeros(4), jnp.zeros(4, jnp.int32), (latents, jnp.zeros((1, 5, 7))))

    exact = [(start(np.full((2, 2, 1), 2.0)), None)]
    assert bench.start_context_error(exact, exact) == 0.0
    assert bench.start_context_error([(start(np.full((2, 2, 1), 2.5)), None)], exact) == pytest.approx(0.25)


def test_the_frames_drawn_are_the_simulators_beside_the_real_ones(tmp_path):
    """``--frames K``: per variant the first K trajectories' frames, decision by decision. A faithful simulator's
    imagined frames equal the real ones (both start at the start frame) and the rows' figures are those of a run
    that draws nothing; a noisy one's differ after the start; the image holds both rows of every trajectory."""
    import cv2

    faithful = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim)
    noisy = toy_simulator(frame_size=8, chunk_len=CFG.chunk_len, proprio_dim=CFG.proprio_dim, noise=0.08)
    k = 3
    drawn = _measure({"faithful": faithful, "noisy": noisy}, real=False, keep_frames=k, frames_dir=str(tmp_path))
    plain = _measure({"faithful": faithful, "noisy": noisy}, real=False)
    timeless = lambda out: [{k: v for k, v in row.items() if k != "seconds"} for row in out["variants"]]  # noqa: E731
    assert timeless(drawn) == timeless(plain)  # drawing the frames changes no figure
    c, s = CFG.imagined.max_chunks, CFG.image_size
    saved = {name: np.load(tmp_path / f"frames_{name}.npz") for name in ("faithful", "noisy")}
    for arrays in saved.values():
        assert arrays["imagined"].shape == arrays["real"].shape == (k, c, s, s, 3)
        assert arrays["imagined"].dtype == np.uint8
        np.testing.assert_array_equal(arrays["imagined"][:, 0], arrays["real"][:, 0])  # the same start frame
    assert np.abs(saved["faithful"]["imagined"].astype(int) - saved["faithful"]["real"].astype(int)).max() <= 1
    assert np.abs(saved["noisy"]["imagined"][:, 1:].astype(int) - saved["noisy"]["real"][:, 1:].astype(int)).max() > 10
    image = cv2.imread(str(tmp_path / "frames_noisy.png"))[..., ::-1]
    assert image.shape == (k * (2 * s + 6), c * (s + 2), 3)
    np.testing.assert_array_equal(image[s + 2:2 * s + 2, :s], saved["noisy"]["real"][0, 0])
    np.testing.assert_array_equal(image[:s, s + 2:2 * s + 2], saved["noisy"]["imagined"][0, 1])
    with pytest.raises(ValueError, match="frames_dir"):
        _measure({"faithful": faithful}, real=False, keep_frames=k)
    with pytest.raises(ValueError, match="must both be"):
        bench.write_frames(str(tmp_path / "bad"), saved["noisy"]["imagined"], saved["noisy"]["real"][:1])
