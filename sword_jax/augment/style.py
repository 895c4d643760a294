"""Style parameters, the training / held-out split of the style space, and segmentation classes.

A :class:`Style` is a pytree of float32 / int32 arrays describing one episode's appearance: the
same style is applied to every frame of the episode. Styles are drawn by :func:`sample_style`
from one of two *disjoint* regions of the style space:

* ``"train"``: moderate global colour changes, the training palette (``TRAIN_PALETTE``) and the
  training textures (plain, wood grain, checker, value noise), weak relighting.
* ``"heldout"``: stronger / different global colour changes, a disjoint palette
  (``HELDOUT_PALETTE``), different textures (stripes, marble, polka dots), stronger relighting.

Every *split-defining* parameter (listed in ``SPLIT_RANGES`` plus the palette indices and
texture ids) has disjoint training and held-out sets, so any single parameter tells the two
apart. :func:`assert_training_style` (host side) raises :class:`HeldOutStyleError` unless every
split-defining parameter of every style in a (possibly batched) ``Style`` lies in the training
set; the training pipeline calls it on every style it did not sample itself.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

# ---------------------------------------------------------------------------------------------
# Segmentation classes.


@dataclasses.dataclass(frozen=True)
class SegClasses:
    """Which segmentation ids form each region. Hashable, so it is a static jit argument.

    The default convention (until ``sim/render.py`` defines its own) is background 0, table 1,
    robot 2, objects 3, fixtures 4. Ids not listed in any group are left alone by the region
    transforms (but still see the global colour and lighting changes).
    """

    background: tuple[int, ...] = (0,)
    table: tuple[int, ...] = (1,)
    robot: tuple[int, ...] = (2,)
    objects: tuple[int, ...] = (3,)
    fixtures: tuple[int, ...] = (4,)

    def __post_init__(self):
        seen: dict[int, str] = {}
        for group in ("background", "table", "robot", "objects", "fixtures"):
            ids = getattr(self, group)
            if not isinstance(ids, tuple) or not all(isinstance(i, (int, np.integer)) for i in ids):
                raise TypeError(f"SegClasses.{group} must be a tuple of ints, got {ids!r}")
            for i in ids:
                if i in seen:
                    raise ValueError(f"SegClasses: id {i} is in both {seen[i]!r} and {group!r}")
                seen[i] = group

    @classmethod
    def from_mapping(cls, mapping: dict[str, int | tuple[int, ...]]) -> SegClasses:
        """Build from ``{"table": 1, "robot": (2, 5), ...}`` (missing groups become empty)."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(mapping) - known
        if unknown:
            raise KeyError(f"SegClasses.from_mapping: unknown groups {sorted(unknown)}; known {sorted(known)}")
        kwargs = {g: (v,) if isinstance(v, (int, np.integer)) else tuple(v) for g, v in mapping.items()}
        return cls(**{g: kwargs.get(g, ()) for g in known})

    @classmethod
    def from_class_names(cls, class_names: tuple[str, ...], fixtures: tuple[str, ...] = ()) -> SegClasses:
        """From a renderer's class names (``sim.render_classes``: ids 0/1/2 = background/table/robot,
        then one id per object or fixture; names in ``fixtures`` are fixtures, the rest objects)."""
        names = tuple(class_names)
        if names[:3] != ("background", "table", "robot"):
            raise ValueError(f"SegClasses.from_class_names: ids 0-2 must be background/table/robot, got {names[:3]}")
        unknown = set(fixtures) - set(names)
        if unknown:
            raise KeyError(f"SegClasses.from_class_names: fixtures {sorted(unknown)} not among {names}")
        rest = range(3, len(names))
        return cls(
            background=(0,), table=(1,), robot=(2,),
            objects=tuple(i for i in rest if names[i] not in fixtures),
            fixtures=tuple(i for i in rest if names[i] in fixtures),
        )

    def mask(self, seg: Int[Array, "*s"], group: str) -> jax.Array:
        """Boolean mask of the pixels of ``group``."""
        ids = getattr(self, group)
        if not ids:
            return jnp.zeros(seg.shape, bool)
        return jnp.isin(seg, jnp.asarray(ids, seg.dtype))


DEFAULT_CLASSES = SegClasses()

# ---------------------------------------------------------------------------------------------
# Palettes and textures.

# Colours (linear-ish RGB in [0, 1]). Every training colour is at Chebyshev distance > 2 * jitter
# from every held-out colour, so jittered colours of the two palettes can never coincide.
TRAIN_PALETTE = np.array(
    [
        [0.80, 0.80, 0.78], [0.55, 0.55, 0.55], [0.25, 0.25, 0.27], [0.62, 0.45, 0.30],
        [0.45, 0.30, 0.18], [0.78, 0.66, 0.48], [0.30, 0.42, 0.62], [0.20, 0.30, 0.45],
        [0.35, 0.55, 0.35], [0.72, 0.30, 0.25], [0.85, 0.62, 0.20], [0.60, 0.62, 0.70],
    ],
    np.float32,
)
HELDOUT_PALETTE = np.array(
    [
        [0.95, 0.20, 0.70], [0.10, 0.85, 0.85], [0.60, 0.95, 0.10], [0.45, 0.10, 0.80],
        [0.98, 0.98, 0.30], [0.05, 0.05, 0.55], [0.95, 0.45, 0.05], [0.10, 0.60, 0.20],
    ],
    np.float32,
)
PALETTE = np.concatenate([TRAIN_PALETTE, HELDOUT_PALETTE])  # global index space
TRAIN_COLORS = tuple(range(len(TRAIN_PALETTE)))
HELDOUT_COLORS = tuple(range(len(TRAIN_PALETTE), len(PALETTE)))
COLOR_JITTER = 0.04

TEXTURES = ("plain", "wood", "checker", "noise", "stripes", "marble", "dots")
TRAIN_TEXTURES = (0, 1, 2, 3)
HELDOUT_TEXTURES = (4, 5, 6)

# Split-defining scalar parameters: (training intervals, held-out intervals), each disjoint.
SPLIT_RANGES: dict[str, tuple[tuple[tuple[float, float], ...], tuple[tuple[float, float], ...]]] = {
    "brightness": (((0.8, 1.2),), ((0.6, 0.72), (1.3, 1.45))),
    "saturation": (((0.7, 1.3),), ((0.3, 0.55), (1.5, 1.8))),
    "hue_shift": (((-0.05, 0.05),), ((-0.3, -0.12), (0.12, 0.3))),  # turns
    "temperature": (((-0.35, 0.35),), ((-0.85, -0.5), (0.5, 0.85))),
    "light_strength": (((0.0, 0.3),), ((0.4, 0.6),)),
    "gradient_strength": (((0.0, 0.12),), ((0.18, 0.3),)),
}
TEXTURE_SCALE = (((3.0, 10.0),), ((14.0, 24.0),))  # cycles per metre, per split
MIX_RANGE = (0.7, 1.0)  # region recolouring strength; shared by both splits (not split-defining)
SPLITS = ("train", "heldout")


class RegionStyle(NamedTuple):
    """Albedo replacement for one segmentation region.

    Attributes:
      palette: ``[2]`` int32 palette indices of the two texture colours.
      colors: ``[2, 3]`` float32 colours (palette colour + jitter).
      texture: int32 texture id (index into ``TEXTURES``).
      scale: texture frequency in cycles per metre.
      angle: texture orientation in radians.
      mix: recolouring strength in [0, 1] (0 = region untouched).
    """

    palette: Int[Array, "2"]
    colors: Float[Array, "2 3"]
    texture: Int[Array, ""]
    scale: Float[Array, ""]
    angle: Float[Array, ""]
    mix: Float[Array, ""]


class Style(NamedTuple):
    """One episode's appearance. All leaves are arrays; a batch of styles has leading dims.

    Attributes:
      brightness: multiplicative gain.
      saturation: 0 = grey, 1 = unchanged.
      hue_shift: hue rotation in turns.
      temperature: colour temperature, < 0 cool (blue), > 0 warm (red).
      robot: robot-arm colour transfer (texture always plain).
      table: table colour + texture.
      background: background colour + texture.
      light_dir: ``[3]`` unit light direction in camera coordinates (z toward the camera is -1).
      light_strength: weight of depth-normal Lambertian relighting.
      gradient_angle: direction of the image-plane illumination gradient (radians).
      gradient_strength: its amplitude.
      texture_seed: int32 seed of the procedural noise.
    """

    brightness: Float[Array, ""]
    saturation: Float[Array, ""]
    hue_shift: Float[Array, ""]
    temperature: Float[Array, ""]
    robot: RegionStyle
    table: RegionStyle
    background: RegionStyle
    light_dir: Float[Array, "3"]
    light_strength: Float[Array, ""]
    gradient_angle: Float[Array, ""]
    gradient_strength: Float[Array, ""]
    texture_seed: Int[Array, ""]


def _f32(x) -> jax.Array:
    return jnp.asarray(x, jnp.float32)


def identity_style() -> Style:
    """The style that changes nothing (``augment`` returns the frames unchanged)."""
    region = RegionStyle(
        palette=jnp.zeros((2,), jnp.int32), colors=jnp.asarray(PALETTE[[0, 0]]), texture=jnp.int32(0),
        scale=_f32(5.0), angle=_f32(0.0), mix=_f32(0.0),
    )
    return Style(
        brightness=_f32(1.0), saturation=_f32(1.0), hue_shift=_f32(0.0), temperature=_f32(0.0),
        robot=region, table=region, background=region, light_dir=_f32([0.0, 0.0, -1.0]),
        light_strength=_f32(0.0), gradient_angle=_f32(0.0), gradient_strength=_f32(0.0),
        texture_seed=jnp.int32(0),
    )


class _Uniforms:
    """Consumes one vector of U[0, 1) draws: one threefry call per style keeps compiles small."""

    SIZE = 48

    def __init__(self, key: jax.Array):
        self.values = jax.random.uniform(key, (self.SIZE,), jnp.float32)
        self.used = 0

    def take(self, n: int | None = None) -> jax.Array:
        count = 1 if n is None else n
        if self.used + count > self.SIZE:
            raise RuntimeError("style sampler: _Uniforms.SIZE too small")
        out = self.values[self.used:self.used + count]
        self.used += count
        return out[0] if n is None else out

    def between(self, low: float, high: float, n: int | None = None) -> jax.Array:
        return np.float32(low) + self.take(n) * np.float32(high - low)

    def index(self, count: int, n: int | None = None) -> jax.Array:
        return jnp.minimum(jnp.floor(self.take(n) * count).astype(jnp.int32), count - 1)

    def union(self, intervals: tuple[tuple[float, float], ...]) -> jax.Array:
        """Uniform over a union of disjoint (static) intervals."""
        lows = np.array([lo for lo, _ in intervals], np.float32)
        lengths = np.array([hi - lo for lo, hi in intervals], np.float32)
        offsets = np.concatenate([[0.0], np.cumsum(lengths)[:-1]]).astype(np.float32)
        # Shrink by a hair so float rounding never lands past an interval's edge.
        u = self.take() * np.float32(float(lengths.sum()) * (1 - 1e-6))
        index = jnp.clip(jnp.searchsorted(jnp.asarray(offsets), u, side="right") - 1, 0, len(intervals) - 1)
        return jnp.asarray(lows)[index] + (u - jnp.asarray(offsets)[index])


def _sample_region(draw: _Uniforms, split_index: int, *, plain: bool) -> RegionStyle:
    colors_ids = np.asarray((TRAIN_COLORS, HELDOUT_COLORS)[split_index], np.int32)
    palette = jnp.asarray(colors_ids)[draw.index(len(colors_ids), 2)]
    jitter = draw.between(-COLOR_JITTER, COLOR_JITTER, 6).reshape(2, 3)
    colors = jnp.clip(jnp.asarray(PALETTE)[palette] + jitter, 0.0, 1.0)
    textures = np.asarray((TRAIN_TEXTURES, HELDOUT_TEXTURES)[split_index], np.int32)
    texture = jnp.asarray(textures)[draw.index(len(textures))]
    return RegionStyle(
        palette=palette,
        colors=colors,
        texture=jnp.zeros_like(texture) if plain else texture,
        scale=draw.union(TEXTURE_SCALE[split_index]),
        angle=draw.between(0.0, np.pi),
        mix=draw.between(*MIX_RANGE),
    )


@functools.partial(jax.jit, static_argnames=("split",))
def sample_style(key: jax.Array, split: str = "train") -> Style:
    """Draw one style from the ``split`` ("train" | "heldout") region. Jittable, vmappable over keys."""
    if split not in SPLITS:
        raise ValueError(f"sample_style: split must be one of {SPLITS}, got {split!r}")
    s = SPLITS.index(split)
    draw = _Uniforms(key)
    scalars = {name: draw.union(ranges[s]) for name, ranges in SPLIT_RANGES.items()}
    light = jnp.concatenate([draw.between(-1.0, 1.0, 2), _f32([-1.0])])
    robot = _sample_region(draw, s, plain=True)
    table = _sample_region(draw, s, plain=False)
    background = _sample_region(draw, s, plain=False)
    return Style(
        brightness=scalars["brightness"],
        saturation=scalars["saturation"],
        hue_shift=scalars["hue_shift"],
        temperature=scalars["temperature"],
        robot=robot,
        table=table,
        background=background,
        light_dir=light / jnp.linalg.norm(light),
        light_strength=scalars["light_strength"],
        gradient_angle=draw.between(0.0, 2 * np.pi),
        gradient_strength=scalars["gradient_strength"],
        texture_seed=draw.index(1 << 24),
    )


@functools.partial(jax.jit, static_argnames=("num", "split"))
def sample_styles(key: jax.Array, num: int, split: str = "train") -> Style:
    """``num`` independent styles (leading dim ``num`` on every leaf)."""
    return jax.vmap(lambda k: sample_style(k, split))(jax.random.split(key, num))


# ---------------------------------------------------------------------------------------------
# Split membership (host side: needs concrete values).


class HeldOutStyleError(ValueError):
    """A style outside the training region reached the training pipeline."""


def _in_union(values: np.ndarray, intervals) -> np.ndarray:
    inside = np.zeros(values.shape, bool)
    for lo, hi in intervals:
        inside |= (values >= lo) & (values <= hi)
    return inside


def _concrete(style: Style) -> Style:
    leaves = jax.tree.leaves(style)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        raise TypeError("style split checks need concrete values: call them outside jit / vmap")
    return jax.tree.map(np.asarray, style)


def split_violations(style: Style, split: str = "train") -> list[str]:
    """Names of the split-defining parameters of ``style`` (any batch shape) outside ``split``."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    s = SPLITS.index(split)
    st = _concrete(style)
    bad = [name for name, ranges in SPLIT_RANGES.items() if not _in_union(getattr(st, name), ranges[s]).all()]
    allowed_colors = np.asarray((TRAIN_COLORS, HELDOUT_COLORS)[s])
    allowed_textures = np.asarray((TRAIN_TEXTURES, HELDOUT_TEXTURES)[s])
    for region_name in ("robot", "table", "background"):
        region: RegionStyle = getattr(st, region_name)
        if not np.isin(region.palette, allowed_colors).all():
            bad.append(f"{region_name}.palette")
        else:
            expected = PALETTE[region.palette]
            if (np.abs(region.colors - expected) > COLOR_JITTER + 1e-5).any():
                bad.append(f"{region_name}.colors")
        if region_name == "robot":  # always plain: its palette is what splits it
            if (region.texture != 0).any():
                bad.append("robot.texture")
            continue
        if not np.isin(region.texture, allowed_textures).all():
            bad.append(f"{region_name}.texture")
        if not _in_union(region.scale, TEXTURE_SCALE[s]).all():
            bad.append(f"{region_name}.scale")
    return bad


def style_split(style: Style) -> str:
    """"train", "heldout" or "mixed" (parameters from both / neither region) for one style."""
    if not split_violations(style, "train"):
        return "train"
    if not split_violations(style, "heldout"):
        return "heldout"
    return "mixed"


def assert_training_style(style: Style) -> None:
    """Raise :class:`HeldOutStyleError` unless every style in ``style`` is in the training region."""
    bad = split_violations(style, "train")
    if bad:
        raise HeldOutStyleError(
            f"style outside the training region (held-out or unknown) in: {', '.join(bad)}; "
            "held-out styles are for evaluation only"
        )


def style_to_record(style: Style) -> dict:
    """JSON-ready nested dict of lists (for manifests); inverse of :func:`style_from_record`."""
    st = _concrete(style)

    def convert(nt):
        return {k: (convert(v) if isinstance(v, tuple) else np.asarray(v).tolist()) for k, v in nt._asdict().items()}

    return convert(st)


def style_from_record(record: dict) -> Style:
    region = {name: RegionStyle(
        palette=jnp.asarray(record[name]["palette"], jnp.int32),
        colors=_f32(record[name]["colors"]),
        texture=jnp.asarray(record[name]["texture"], jnp.int32),
        scale=_f32(record[name]["scale"]), angle=_f32(record[name]["angle"]), mix=_f32(record[name]["mix"]),
    ) for name in ("robot", "table", "background")}
    scalars = {k: _f32(record[k]) for k in Style._fields if k not in region and k != "texture_seed"}
    return Style(**scalars, **region, texture_seed=jnp.asarray(record["texture_seed"], jnp.int32))
