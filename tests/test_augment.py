"""Structure-guided style augmentation: identity, locality, structure preservation, split, jit/vmap."""

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sword_jax.augment import style as st
from sword_jax.augment.structure import edge_map, segmentation_boundaries, structure_scores
from sword_jax.augment.synthetic import synthetic_episode
from sword_jax.augment.textures import depth_normals, texture
from sword_jax.augment.transforms import augment, augment_batch, augment_styles, color_adjust

SIZE, FRAMES = 32, 2


@pytest.fixture(scope="module")
def episode():
    ep = synthetic_episode(FRAMES, SIZE)
    return {k: jnp.asarray(v) for k, v in ep.items()}


@pytest.fixture(scope="module")
def run():
    fn = jax.jit(lambda f, d, s, style, intensity: augment(f, d, s, style, intensity=intensity))
    return lambda ep, style, intensity=1.0: fn(ep["frames"], ep["depth"], ep["seg"], style, jnp.float32(intensity))


@pytest.fixture(scope="module")
def scores():
    return jax.jit(structure_scores, static_argnames=("classes", "textured"))


def _only(**changes) -> st.Style:
    """The identity style with some fields replaced (regions via dicts of RegionStyle fields)."""
    base = st.identity_style()
    out = {}
    for name, value in changes.items():
        if isinstance(value, dict):
            region = getattr(base, name)
            out[name] = region._replace(**{k: jnp.asarray(v, getattr(region, k).dtype) for k, v in value.items()})
        else:
            out[name] = jnp.asarray(value, getattr(base, name).dtype)
    return base._replace(**out)


def test_identity_and_zero_intensity(episode, run):
    out = run(episode, st.identity_style())
    np.testing.assert_allclose(out, episode["frames"], atol=1e-5)
    styled = st.sample_style(jax.random.key(3), "heldout")
    np.testing.assert_allclose(run(episode, styled, 0.0), episode["frames"], atol=1e-5)
    full = run(episode, styled, 1.0)
    half = run(episode, styled, 0.5)
    d_half = float(jnp.abs(half - episode["frames"]).mean())
    d_full = float(jnp.abs(full - episode["frames"]).mean())
    assert 0.02 < d_half < d_full, (d_half, d_full)
    assert full.dtype == jnp.float32 and float(full.min()) >= 0.0 and float(full.max()) <= 1.0


@pytest.mark.parametrize("region", ["robot", "table", "background"])
def test_region_transform_changes_only_its_mask(episode, run, region):
    style = _only(**{region: {"palette": [15, 17], "colors": st.PALETTE[[15, 17]], "texture": 2, "mix": 1.0}})
    out = run(episode, style)
    changed = np.abs(np.asarray(out) - np.asarray(episode["frames"])).max(-1) > 1e-6
    mask = np.asarray(st.DEFAULT_CLASSES.mask(episode["seg"], region))
    assert not changed[~mask].any(), f"{region} transform changed {changed[~mask].sum()} pixels outside its mask"
    assert changed[mask].mean() > 0.9, f"{region} transform left most of its mask unchanged"


def test_robot_colour_transfer_hits_target_hue_and_keeps_shading(episode, run):
    target = np.array([0.1, 0.8, 0.2], np.float32)
    out = np.asarray(run(episode, _only(robot={"colors": np.stack([target, target]), "mix": 1.0})))
    mask = np.asarray(st.DEFAULT_CLASSES.mask(episode["seg"], "robot"))
    robot_pixels = out[mask]
    mean = robot_pixels.mean(0)
    assert np.argmax(mean) == 1 and mean[1] > 2 * mean[0], mean
    # Shading (luma variation across the arm) survives: correlation with the original luma.
    luma_before = np.asarray(episode["frames"])[mask] @ np.array([0.299, 0.587, 0.114])
    luma_after = robot_pixels @ np.array([0.299, 0.587, 0.114])
    assert np.corrcoef(luma_before, luma_after)[0, 1] > 0.95


def test_global_colour_ops():
    adjust = jax.jit(color_adjust)
    grey = jnp.full((1, 2, 2, 3), 0.5, jnp.float32)
    warm = adjust(grey, _only(temperature=1.0), jnp.float32(1.0))
    assert float(warm[..., 0].mean()) > float(warm[..., 2].mean()) + 0.1
    red = jnp.broadcast_to(jnp.array([0.8, 0.2, 0.2], jnp.float32), (1, 2, 2, 3))
    desat = adjust(red, _only(saturation=0.0), jnp.float32(1.0))
    assert float(jnp.ptp(desat[0, 0, 0])) < 1e-5
    rotated = adjust(red, _only(hue_shift=1 / 3), jnp.float32(1.0))
    assert int(jnp.argmax(rotated[0, 0, 0])) != 0
    bright = adjust(grey, _only(brightness=1.4), jnp.float32(1.0))
    np.testing.assert_allclose(bright, 0.7, atol=1e-5)


def test_relighting_follows_geometry_only(run):
    # Left half: a camera-facing plane; right half: a plane tilted away along x. Relighting must
    # leave the camera-facing plane alone up to the depth step (no halo), and shade the tilted one.
    cols = jnp.arange(SIZE, dtype=jnp.float32)[None, None, :]
    depth = jnp.where(cols < SIZE // 2, 1.0, 1.5 + 0.05 * (cols - SIZE // 2)) * jnp.ones((FRAMES, SIZE, SIZE), jnp.float32)
    flat = {"frames": jnp.full((FRAMES, SIZE, SIZE, 3), 0.5, jnp.float32), "depth": depth,
            "seg": jnp.full((FRAMES, SIZE, SIZE), 7, jnp.int32)}  # 7: in no recoloured group
    out = np.asarray(run(flat, _only(light_dir=[0.6, 0.0, -0.8], light_strength=0.5)))
    np.testing.assert_allclose(out[:, :, : SIZE // 2], 0.5, atol=1e-5)
    assert np.abs(out[:, :, SIZE // 2:] - 0.5).min() > 0.02
    normals = jax.jit(depth_normals, static_argnums=1)(jnp.linspace(1.0, 2.0, 16)[None, :, None] * jnp.ones((1, 16, 16)), 45.0)
    # Depth growing down the image is a ceiling-like plane: its normal points down (+y) and at the camera.
    assert float(normals[0, 8, 8, 1]) > 0.1 and float(normals[0, 8, 8, 2]) < 0


def test_textures_are_in_range_and_distinct():
    coords = jnp.stack(jnp.meshgrid(jnp.linspace(0, 1, 24), jnp.linspace(0, 1, 24)), -1)
    all_maps = jax.jit(jax.vmap(lambda i: texture(coords, i, jnp.float32(6.0), jnp.float32(0.3), jnp.int32(5))))
    maps = list(np.asarray(all_maps(jnp.arange(len(st.TEXTURES), dtype=jnp.int32))))
    for i, m in enumerate(maps):
        assert m.min() >= 0.0 and m.max() <= 1.0, st.TEXTURES[i]
        assert (m.std() > 0.05) == (i != 0), st.TEXTURES[i]
    for i in range(1, len(maps)):
        for j in range(i + 1, len(maps)):
            assert np.abs(maps[i] - maps[j]).mean() > 0.05, (st.TEXTURES[i], st.TEXTURES[j])


@pytest.mark.parametrize("split, min_boundary_recall, min_untextured_f1", [("train", 0.9, 0.9), ("heldout", 0.75, 0.8)])
def test_structure_preserved(episode, run, scores, split, min_boundary_recall, min_untextured_f1):
    """Thresholds: segmentation-boundary recall (1 px) >= 0.9 train / 0.75 held-out for every style (and
    depth-discontinuity recall >= that share of the raw frames' own),
    edge-F1 >= 0.9 / 0.8 with textures off, no invented edges on untextured surfaces."""
    recalls = []
    for i in range(6):
        style = st.sample_style(jax.random.key(100 + i), split)
        full = scores(episode["frames"], run(episode, style), episode["seg"], depth=episode["depth"])
        flat = style._replace(table=style.table._replace(mix=jnp.float32(0)),
                              background=style.background._replace(mix=jnp.float32(0)))
        untextured = scores(episode["frames"], run(episode, flat), episode["seg"])
        assert float(full["boundary_recall"]) >= min_boundary_recall, (i, full)
        assert float(untextured["edge_f1"]) >= min_untextured_f1, (i, untextured)
        assert float(full["off_boundary_new_edges"]) <= 0.02, (i, full)
        assert float(full["depth_edge_recall"]) >= min_boundary_recall * float(full["depth_edge_recall_original"]), (i, full)
        recalls.append(float(full["boundary_recall"]))
    assert np.mean(recalls) >= 0.9


def test_structure_measure_detects_broken_structure(episode, scores):
    # A shifted image breaks alignment with the segmentation: the measure must notice.
    shifted = jnp.roll(episode["frames"], 5, axis=2)
    s = scores(episode["frames"], shifted, episode["seg"])
    assert float(s["edge_f1"]) < 0.8 and float(s["boundary_recall"]) < 0.8, s
    assert segmentation_boundaries(episode["seg"]).any() and edge_map(episode["frames"]).any()


def test_same_style_every_frame(run):
    ep = synthetic_episode(FRAMES, SIZE)
    still = {k: jnp.asarray(np.repeat(v[:1], FRAMES, axis=0)) for k, v in ep.items()}  # a static scene
    out = np.asarray(run(still, st.sample_style(jax.random.key(9), "train")))
    np.testing.assert_allclose(out[1:], np.broadcast_to(out[:1], out[1:].shape), atol=1e-6)


def test_split_disjoint_over_many_samples():
    train = st.sample_styles(jax.random.key(0), 256, "train")
    held = st.sample_styles(jax.random.key(1), 256, "heldout")
    assert st.split_violations(train, "train") == []
    assert st.split_violations(held, "heldout") == []
    st.assert_training_style(train)
    for i in range(0, 256, 17):
        one = jax.tree.map(lambda x, i=i: x[i], held)
        assert st.style_split(one) == "heldout"
        with pytest.raises(st.HeldOutStyleError):
            st.assert_training_style(one)
    # Every split-defining parameter separates the splits on its own.
    for name, (train_ranges, held_ranges) in st.SPLIT_RANGES.items():
        assert not st._in_union(np.asarray(getattr(held, name)), train_ranges).any(), name
        assert not st._in_union(np.asarray(getattr(train, name)), held_ranges).any(), name
    assert not set(np.unique(train.table.texture)) & set(st.HELDOUT_TEXTURES)
    assert not set(np.unique(np.asarray(train.table.palette))) & set(st.HELDOUT_COLORS)
    # Palettes stay apart after jitter.
    gap = np.abs(st.TRAIN_PALETTE[:, None] - st.HELDOUT_PALETTE[None]).max(-1).min()
    assert gap > 2 * st.COLOR_JITTER


def test_single_heldout_parameter_is_caught():
    style = st.sample_style(jax.random.key(4), "train")
    for leaked in (style._replace(hue_shift=jnp.float32(0.2)),
                   style._replace(table=style.table._replace(texture=jnp.int32(5))),
                   style._replace(robot=style.robot._replace(palette=jnp.array([13, 13], jnp.int32),
                                                            colors=jnp.asarray(st.PALETTE[[13, 13]])))):
        with pytest.raises(st.HeldOutStyleError):
            st.assert_training_style(leaked)
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda s: st.assert_training_style(s))(style)


def test_style_record_round_trip():
    style = st.sample_style(jax.random.key(8), "heldout")
    back = st.style_from_record(st.style_to_record(style))
    chex.assert_trees_all_close(style, back)


def test_jit_vmap_determinism_and_traces(episode):
    frames = jnp.stack([episode["frames"]] * 3)
    depth = jnp.stack([episode["depth"]] * 3)
    seg = jnp.stack([episode["seg"]] * 3)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def batch(frames, depth, seg, key):
        styles = st.sample_styles(key, 3, "train")
        return augment_batch(frames, depth, seg, styles)

    a = batch(frames, depth, seg, jax.random.key(0))
    b = batch(frames, depth, seg, jax.random.key(0))
    c = batch(frames, depth, seg, jax.random.key(1))
    np.testing.assert_array_equal(a, b)
    assert float(jnp.abs(a - c).mean()) > 0.01
    assert float(jnp.abs(a[0] - a[1]).mean()) > 0.01  # one style per episode
    single = augment(episode["frames"], episode["depth"], episode["seg"],
                     jax.tree.map(lambda x: x[1], st.sample_styles(jax.random.key(0), 3, "train")))
    np.testing.assert_allclose(single, a[1], atol=1e-5)
    # Per-episode intensity; and the texture switch stays a conditional (vmapped, it becomes every
    # texture at every pixel, which XLA's GPU compiler takes minutes over).
    styles = st.sample_styles(jax.random.key(0), 3, "train")
    mixed = augment_batch(frames, depth, seg, styles, intensity=jnp.array([0.0, 1.0, 1.0]))
    np.testing.assert_allclose(mixed[0], frames[0], atol=1e-5)
    np.testing.assert_allclose(mixed[1], a[1], atol=1e-5)
    assert " cond[" in str(jax.make_jaxpr(lambda f, d, g, s: augment_batch(f, d, g, s))(frames, depth, seg, styles))
    # One episode under each style: the batch's rows, since its episodes are copies of that one.
    np.testing.assert_allclose(augment_styles(frames[0], depth[0], seg[0], styles), a, atol=1e-5)
    # The optional key re-seeds textures only.
    style = st.sample_style(jax.random.key(2), "train")._replace(table=st.sample_style(jax.random.key(2)).table._replace(texture=jnp.int32(3)))
    k1 = augment(episode["frames"], episode["depth"], episode["seg"], style, key=jax.random.key(1))
    k2 = augment(episode["frames"], episode["depth"], episode["seg"], style, key=jax.random.key(2))
    table = np.asarray(st.DEFAULT_CLASSES.mask(episode["seg"], "table"))
    diff = np.abs(np.asarray(k1) - np.asarray(k2)).max(-1)
    assert diff[table].mean() > 1e-3 and diff[~table & ~np.asarray(st.DEFAULT_CLASSES.mask(episode["seg"], "background"))].max() < 1e-6


@pytest.mark.parametrize(
    "frames, depth, seg, match",
    [
        (np.zeros((2, 8, 8), np.float32), np.ones((2, 8, 8), np.float32), np.zeros((2, 8, 8), np.int32), "frames must be"),
        (np.zeros((2, 8, 8, 3), np.float32), np.ones((2, 8, 9), np.float32), np.zeros((2, 8, 8), np.int32), "depth must be"),
        (np.full((2, 8, 8, 3), 2.0, np.float32), np.ones((2, 8, 8), np.float32), np.zeros((2, 8, 8), np.int32), r"\[0, 1\]"),
        (np.full((2, 8, 8, 3), np.nan, np.float32), np.ones((2, 8, 8), np.float32), np.zeros((2, 8, 8), np.int32), "NaN"),
        (np.zeros((2, 8, 8, 3), np.uint8), np.ones((2, 8, 8), np.float32), np.zeros((2, 8, 8), np.int32), "float"),
        (np.zeros((2, 8, 8, 3), np.float32), np.ones((2, 8, 8), np.float32), np.zeros((2, 8, 8), np.float32), "integer"),
    ],
)
def test_bad_inputs_are_named(frames, depth, seg, match):
    with pytest.raises((ValueError, TypeError), match=match):
        augment(frames, depth, seg, st.identity_style())


def test_seg_classes():
    with pytest.raises(ValueError, match="both"):
        st.SegClasses(table=(1,), robot=(1,))
    classes = st.SegClasses.from_class_names(("background", "table", "robot", "bowl", "cabinet"), fixtures=("cabinet",))
    assert classes.objects == (3,) and classes.fixtures == (4,)
    assert st.SegClasses.from_mapping({"robot": (2, 5)}).robot == (2, 5)
