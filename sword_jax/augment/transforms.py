"""Structure-guided style augmentation: change appearance, keep geometry and layout.

Convention: frames are float in **[0, 1]** (``[T, H, W, 3]``), depth is metres (``[T, H, W]``,
non-finite = far), segmentation is an integer class map (``[T, H, W]``) whose ids are grouped by
:class:`~sword_jax.augment.style.SegClasses`. Use :func:`to_unit_range` / :func:`to_signed_range`
to move between this and the VAE's [-1, 1].

Order of operations (each a pure function, each the identity at zero strength):

1. region albedo replacement, keeping the original shading: robot colour transfer (robot mask),
   table colour + procedural texture (table mask), background colour + texture (background mask);
2. relighting: Lambertian term from depth normals and an image-plane illumination gradient;
3. global colour: brightness, colour temperature, saturation, hue rotation; clip to [0, 1].

Depth and segmentation are never changed, and textures are glued to the depth-derived surface,
so the scene's structure (object outlines, layout, geometry) is what the frames still show.
``intensity`` in [0, 1] scales every parameter's departure from the identity.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from sword_jax.augment.style import DEFAULT_CLASSES, RegionStyle, SegClasses, Style
from sword_jax.augment.textures import camera_points, depth_normals, texture

LUMA = np.array([0.299, 0.587, 0.114], np.float32)
_RGB_TO_YIQ = np.array([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]], np.float32)
_YIQ_TO_RGB = np.linalg.inv(_RGB_TO_YIQ).astype(np.float32)
TEMPERATURE_GAIN = np.float32(0.3)  # red/blue gain change at temperature +-1


def to_unit_range(frames: jax.Array, source: str) -> Float[Array, "..."]:
    """Frames from ``source`` ("uint8" | "signed" ([-1, 1]) | "unit") to float32 [0, 1]."""
    if source == "uint8":
        return frames.astype(jnp.float32) / np.float32(255.0)
    if source == "signed":
        return (frames.astype(jnp.float32) + 1) * np.float32(0.5)
    if source == "unit":
        return frames.astype(jnp.float32)
    raise ValueError(f"to_unit_range: source must be uint8|signed|unit, got {source!r}")


def to_signed_range(frames: Float[Array, "..."]) -> Float[Array, "..."]:
    """[0, 1] -> [-1, 1] (what the VAE encodes)."""
    return frames * np.float32(2.0) - np.float32(1.0)


def luma(rgb: Float[Array, "... 3"]) -> Float[Array, "..."]:
    return rgb @ jnp.asarray(LUMA)


def check_inputs(frames, depth, seg) -> None:
    """Shape / dtype checks (static, so they run under jit too); value checks when concrete."""
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"augment: frames must be [T, H, W, 3], got shape {frames.shape}")
    if depth.shape != frames.shape[:-1]:
        raise ValueError(f"augment: depth must be [T, H, W] = {frames.shape[:-1]}, got {depth.shape}")
    if seg.shape != frames.shape[:-1]:
        raise ValueError(f"augment: seg must be [T, H, W] = {frames.shape[:-1]}, got {seg.shape}")
    if not jnp.issubdtype(frames.dtype, jnp.floating):
        raise TypeError(f"augment: frames must be float in [0, 1] (see to_unit_range), got {frames.dtype}")
    if not jnp.issubdtype(seg.dtype, jnp.integer):
        raise TypeError(f"augment: seg must be an integer class map, got {seg.dtype}")
    if any(isinstance(x, jax.core.Tracer) for x in (frames, depth)):
        return
    f = np.asarray(frames)
    if not np.isfinite(f).all():
        raise ValueError("augment: frames contain NaN/inf")
    if f.min() < -1e-3 or f.max() > 1 + 1e-3:
        raise ValueError(
            f"augment: frames must be in [0, 1], got range [{f.min():.3g}, {f.max():.3g}] "
            "(convert [-1, 1] or uint8 frames with to_unit_range)"
        )
    if np.isnan(np.asarray(depth)).any():
        raise ValueError("augment: depth contains NaN (use inf for 'no surface')")


# ---------------------------------------------------------------------------------------------
# Individual transforms (pure, exact identity at strength 0).


def recolor_region(
    frames: Float[Array, "t h w 3"],
    mask: Float[Array, "t h w"],
    coords: Float[Array, "t h w 2"],
    region: RegionStyle,
    seed: Int[Array, ""],
    strength: Float[Array, ""],
) -> Float[Array, "t h w 3"]:
    """Replace the albedo inside ``mask`` with a (textured) colour, keeping the original shading.

    Shading is the pixel's luma over the region's mean luma (over all frames, so the change is
    the same in every frame of the episode); pixels outside ``mask`` are returned bit-exactly.
    """
    maskf = mask.astype(jnp.float32)
    y = luma(frames)
    mean_luma = jnp.sum(y * maskf) / jnp.maximum(jnp.sum(maskf), 1.0)
    shading = jnp.clip(y / jnp.maximum(mean_luma, np.float32(1e-3)), 0.0, 2.5)
    weight = texture(coords, region.texture, region.scale, region.angle, seed)[..., None]
    albedo = region.colors[0] * (1 - weight) + region.colors[1] * weight
    recolored = jnp.clip(albedo * shading[..., None], 0.0, 1.0)
    mix = region.mix * strength
    return jnp.where(mask[..., None], frames + mix * (recolored - frames), frames)


def relight(
    frames: Float[Array, "t h w 3"],
    depth: Float[Array, "t h w"],
    style: Style,
    strength: Float[Array, ""],
    fov_deg: float,
) -> Float[Array, "t h w 3"]:
    """Multiply by a Lambertian term from depth normals and a directional image-plane gradient.

    The gain depends on geometry only (normals, pixel position), so flat regions of one depth
    get one gain: it cannot draw edges that are not in the depth map.
    """
    normals = depth_normals(depth, fov_deg)
    lambert = jnp.clip(normals @ style.light_dir, 0.0, 1.0)
    flat = jnp.clip(-style.light_dir[2], 0.0, 1.0)  # response of a camera-facing plane
    light_gain = 1 + style.light_strength * strength * 2 * (lambert - flat)
    h, w = depth.shape[-2:]
    ys = jnp.linspace(-1.0, 1.0, h, dtype=jnp.float32)[:, None]
    xs = jnp.linspace(-1.0, 1.0, w, dtype=jnp.float32)[None, :]
    ramp = xs * jnp.cos(style.gradient_angle) + ys * jnp.sin(style.gradient_angle)
    gradient_gain = 1 + style.gradient_strength * strength * ramp
    gain = jnp.clip(light_gain * gradient_gain, 0.0, 3.0)
    return frames * gain[..., None]


def color_adjust(frames: Float[Array, "... 3"], style: Style, strength: Float[Array, ""]) -> Float[Array, "... 3"]:
    """Brightness, colour temperature, saturation and hue rotation, then clip to [0, 1]."""
    out = frames * jnp.power(style.brightness, strength)
    t = style.temperature * strength
    gains = jnp.stack([1 + TEMPERATURE_GAIN * t, jnp.ones_like(t), 1 - TEMPERATURE_GAIN * t])
    out = out * (gains / (gains @ jnp.asarray(LUMA)))  # keep luma of grey
    y = luma(out)[..., None]
    out = y + jnp.power(style.saturation, strength) * (out - y)
    angle = np.float32(2 * np.pi) * style.hue_shift * strength
    c, s = jnp.cos(angle), jnp.sin(angle)
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    rotation = jnp.stack([jnp.stack([one, zero, zero]), jnp.stack([zero, c, -s]), jnp.stack([zero, s, c])])
    matrix = jnp.asarray(_YIQ_TO_RGB) @ rotation @ jnp.asarray(_RGB_TO_YIQ)
    out = out @ matrix.T
    return jnp.clip(out, 0.0, 1.0)


# ---------------------------------------------------------------------------------------------
# The whole augmentation.


@functools.partial(jax.jit, static_argnames=("classes", "fov_deg"))
def _augment(frames, depth, seg, style, seed_offset, intensity, classes, fov_deg):
    strength = jnp.clip(jnp.asarray(intensity, jnp.float32), 0.0, 1.0)
    frames = frames.astype(jnp.float32)
    points = camera_points(depth, fov_deg)
    seed = style.texture_seed ^ seed_offset
    table_coords = points[..., (0, 2)]  # horizontal plane: (X, Z)
    wall_coords = points[..., (0, 1)]  # background: (X, Y)
    out = recolor_region(frames, classes.mask(seg, "robot"), table_coords, style.robot, seed, strength)
    out = recolor_region(out, classes.mask(seg, "table"), table_coords, style.table, seed + 101, strength)
    out = recolor_region(out, classes.mask(seg, "background"), wall_coords, style.background, seed + 202, strength)
    out = relight(out, depth, style, strength, fov_deg)
    return color_adjust(out, style, strength)


def augment(
    frames: Float[Array, "t h w 3"],
    depth: Float[Array, "t h w"],
    seg: Int[Array, "t h w"],
    style: Style,
    *,
    key: jax.Array | None = None,
    intensity: float | Float[Array, ""] = 1.0,
    classes: SegClasses = DEFAULT_CLASSES,
    fov_deg: float = 45.0,
) -> Float[Array, "t h w 3"]:
    """Restyle one episode's frames; pure, jittable, vmappable. Restyle many with :func:`augment_batch`
    (a ``lax.map``: vmapped over styles, this function's texture switch compiles for minutes on GPU).

    Args:
      frames: ``[T, H, W, 3]`` float RGB in [0, 1].
      depth: ``[T, H, W]`` metres (non-finite = no surface / far).
      seg: ``[T, H, W]`` integer class map, grouped by ``classes``.
      style: one :class:`Style` (the same for every frame of the episode).
      key: optional; re-seeds the procedural textures (same style, another texture instance).
        ``None`` uses ``style.texture_seed`` alone, so the result is a function of the style.
      intensity: in [0, 1]; 0 returns ``frames`` (up to float rounding), 1 the full style.
      classes: segmentation id groups (static).
      fov_deg: vertical field of view of the camera (static), for metric texture coordinates.

    Returns:
      ``[T, H, W, 3]`` float32 frames in [0, 1].
    """
    check_inputs(frames, depth, seg)
    if key is None:
        seed_offset = jnp.int32(0)
    else:
        seed_offset = jax.random.randint(key, (), 0, 2**30, jnp.int32)
    return _augment(frames, depth, seg, style, seed_offset, intensity, classes, float(fov_deg))


def augment_batch(
    frames: Float[Array, "b t h w 3"],
    depth: Float[Array, "b t h w"],
    seg: Int[Array, "b t h w"],
    styles: Style,
    *,
    intensity: float | Float[Array, ""] = 1.0,
    classes: SegClasses = DEFAULT_CLASSES,
    fov_deg: float = 45.0,
) -> Float[Array, "b t h w 3"]:
    """:func:`augment` over a batch of episodes, one style each (leading dim ``b``).

    ``intensity`` is a scalar or one per episode (``[b]``). The episodes are mapped (``lax.map``), not
    vmapped: vmapped over styles whose texture ids differ, the texture ``switch`` becomes every
    texture at every pixel, and XLA's GPU compiler takes minutes over that (on one H200, at the small
    VAE batch of 8 clips x 9 frames x 128 px: over 110 s vmapped, 9 s mapped; 1-2 s either way on
    CPU). Use this, not ``vmap(augment)``, to restyle many episodes.
    """
    amounts = jnp.broadcast_to(jnp.asarray(intensity, jnp.float32), frames.shape[:1])

    def one(args):
        f, d, s, st, amount = args
        return augment(f, d, s, st, intensity=amount, classes=classes, fov_deg=fov_deg)

    return jax.lax.map(one, (frames, depth, seg, styles, amounts))


def augment_styles(
    frames: Float[Array, "t h w 3"],
    depth: Float[Array, "t h w"],
    seg: Int[Array, "t h w"],
    styles: Style,
    *,
    intensity: float | Float[Array, ""] = 1.0,
    classes: SegClasses = DEFAULT_CLASSES,
    fov_deg: float = 45.0,
) -> Float[Array, "c t h w 3"]:
    """One episode under each of ``c`` styles (leading dim of ``styles``): mapped like
    :func:`augment_batch`, for the same reason (a vmapped texture switch compiles for minutes on GPU)."""
    return jax.lax.map(
        lambda style: augment(frames, depth, seg, style, intensity=intensity, classes=classes, fov_deg=fov_deg), styles)
