"""Geometry from depth (camera-space points, normals) and procedural textures.

Textures are evaluated in *metric* coordinates recovered from depth with a pinhole camera of
vertical field of view ``fov_deg`` (the LIBERO agent-view camera is static), so a texture is
glued to the surface: it foreshortens with the table and does not swim between frames.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

NEAR, FAR = 0.05, 20.0  # metres: depth clamp (invalid / infinite depth becomes FAR)
MAX_SLOPE = 6.0  # clamp of |dz/dx| so depth discontinuities give finite normals


def camera_points(depth: Float[Array, "*t h w"], fov_deg: float) -> Float[Array, "*t h w 3"]:
    """Camera-space points (X right, Y down, Z forward, metres) of every pixel."""
    h, w = depth.shape[-2:]
    z = jnp.clip(jnp.where(jnp.isfinite(depth), depth, FAR), NEAR, FAR).astype(jnp.float32)
    tan_half = np.float32(np.tan(np.deg2rad(fov_deg) / 2))
    ys = (np.arange(h, dtype=np.float32) + 0.5) / h * 2 - 1
    xs = ((np.arange(w, dtype=np.float32) + 0.5) / w * 2 - 1) * np.float32(w / h)
    x = jnp.asarray(xs)[None, :] * tan_half * z
    y = jnp.asarray(ys)[:, None] * tan_half * z
    return jnp.stack([x, y, z], axis=-1)


def _smooth_side_difference(z: Float[Array, "*t h w"], axis: int) -> Float[Array, "*t h w"]:
    """Per-pixel slope from the one-sided difference that agrees with the next one on its side.

    At a depth discontinuity one side lies on the same surface (its two differences agree), so
    the slope, and the relit shading, stays that surface's instead of drawing a dark or bright
    halo along the outline.
    """
    n = z.shape[axis]
    take = functools.partial(jax.lax.slice_in_dim, z, axis=axis)
    head, tail = take(0, 1), take(n - 1, n)
    head_step, tail_step = take(1, 2) - head, tail - take(n - 2, n - 1)
    # Linear extrapolation by two pixels at the border, so border pixels keep their surface's slope.
    padded = jnp.concatenate([head - 2 * head_step, head - head_step, z, tail + tail_step, tail + 2 * tail_step],
                             axis=axis)
    at = lambda offset: jax.lax.slice_in_dim(padded, 2 + offset, 2 + offset + n, axis=axis)  # noqa: E731
    forward, forward_next = at(1) - z, at(2) - at(1)
    backward, backward_prev = z - at(-1), at(-1) - at(-2)
    use_forward = jnp.abs(forward - forward_next) < jnp.abs(backward - backward_prev)
    return jnp.where(use_forward, forward, backward)


def depth_normals(depth: Float[Array, "*t h w"], fov_deg: float) -> Float[Array, "*t h w 3"]:
    """Unit surface normals (pointing toward the camera, z < 0) from depth finite differences."""
    points = camera_points(depth, fov_deg)
    z = points[..., 2]
    h = depth.shape[-2]
    pixel_metres = z * np.float32(2 * np.tan(np.deg2rad(fov_deg) / 2) / h)  # metric size of a pixel
    dz_dx = _smooth_side_difference(z, axis=-1) / pixel_metres
    dz_dy = _smooth_side_difference(z, axis=-2) / pixel_metres
    dz_dx = jnp.clip(dz_dx, -MAX_SLOPE, MAX_SLOPE)
    dz_dy = jnp.clip(dz_dy, -MAX_SLOPE, MAX_SLOPE)
    n = jnp.stack([dz_dx, dz_dy, -jnp.ones_like(z)], axis=-1)
    return n / jnp.linalg.norm(n, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Hash value noise.


def _hash2(i: Int[Array, "*s"], j: Int[Array, "*s"], seed: Int[Array, ""]) -> Float[Array, "*s"]:
    """Deterministic uniform [0, 1) per integer lattice point (uint32 integer hash)."""
    h = (i.astype(jnp.uint32) * jnp.uint32(0x8DA6B343)) ^ (j.astype(jnp.uint32) * jnp.uint32(0xD8163841))
    h = h ^ (seed.astype(jnp.uint32) * jnp.uint32(0xCB1AB31F))
    h = (h ^ (h >> jnp.uint32(16))) * jnp.uint32(0x7FEB352D)
    h = (h ^ (h >> jnp.uint32(15))) * jnp.uint32(0x846CA68B)
    h = h ^ (h >> jnp.uint32(16))
    return (h >> jnp.uint32(8)).astype(jnp.float32) * np.float32(1.0 / (1 << 24))


def value_noise(u: Float[Array, "*s"], v: Float[Array, "*s"], seed: Int[Array, ""]) -> Float[Array, "*s"]:
    """Smooth value noise in [0, 1] with unit lattice spacing."""
    iu, iv = jnp.floor(u), jnp.floor(v)
    fu, fv = u - iu, v - iv
    su, sv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    iu, iv = iu.astype(jnp.int32), iv.astype(jnp.int32)
    n00, n10 = _hash2(iu, iv, seed), _hash2(iu + 1, iv, seed)
    n01, n11 = _hash2(iu, iv + 1, seed), _hash2(iu + 1, iv + 1, seed)
    return (n00 * (1 - su) + n10 * su) * (1 - sv) + (n01 * (1 - su) + n11 * su) * sv


def fbm(u: Float[Array, "*s"], v: Float[Array, "*s"], seed: Int[Array, ""], octaves: int = 3) -> Float[Array, "*s"]:
    """Fractal value noise in [0, 1]."""
    total, norm, amp, freq = jnp.zeros_like(u), 0.0, 1.0, 1.0
    for octave in range(octaves):
        total = total + np.float32(amp) * value_noise(u * np.float32(freq), v * np.float32(freq), seed + octave)
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / np.float32(norm)


# ---------------------------------------------------------------------------------------------
# Textures: each maps metric surface coordinates (already scaled to cycles) to a mix weight in [0, 1].


def _plain(u, v, seed):
    return jnp.zeros_like(u)


def _wood(u, v, seed):
    # Grain along u, rings across v, warped by low-frequency noise.
    warp = fbm(u * np.float32(0.25), v * np.float32(1.0), seed)
    return 0.5 + 0.5 * jnp.sin(np.float32(2 * np.pi) * (v + np.float32(1.5) * warp))


def _checker(u, v, seed):
    return jnp.mod(jnp.floor(u) + jnp.floor(v), 2.0)


def _noise(u, v, seed):
    return fbm(u, v, seed)


def _stripes(u, v, seed):
    return (jnp.mod(u, 1.0) < 0.5).astype(jnp.float32)


def _marble(u, v, seed):
    turbulence = fbm(u * np.float32(0.5), v * np.float32(0.5), seed, octaves=4)
    return 0.5 + 0.5 * jnp.sin(np.float32(np.pi) * (u + v) + np.float32(8.0) * turbulence)


def _dots(u, v, seed):
    du, dv = jnp.mod(u, 1.0) - 0.5, jnp.mod(v, 1.0) - 0.5
    return (du * du + dv * dv < np.float32(0.3**2)).astype(jnp.float32)


TEXTURE_FNS = (_plain, _wood, _checker, _noise, _stripes, _marble, _dots)  # order = style.TEXTURES


def texture(
    coords: Float[Array, "*s 2"],
    texture_id: Int[Array, ""],
    scale: Float[Array, ""],
    angle: Float[Array, ""],
    seed: Int[Array, ""],
) -> Float[Array, "*s"]:
    """Texture ``texture_id`` at metric surface coordinates, ``scale`` cycles per metre, rotated by ``angle``."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    u = (coords[..., 0] * c - coords[..., 1] * s) * scale
    v = (coords[..., 0] * s + coords[..., 1] * c) * scale
    branches = [lambda uv, f=f: f(uv[0], uv[1], seed).astype(jnp.float32) for f in TEXTURE_FNS]
    index = jnp.clip(texture_id, 0, len(TEXTURE_FNS) - 1)
    return jax.lax.switch(index, branches, (u, v))
