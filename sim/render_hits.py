"""Ray-primitive intersections in a geom's local frame, and the surface normal at a hit, for
``sim/render.py``'s ray caster and its tile culling (``sim/render_cull.py``)."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import mujoco
import numpy as np

_PLANE, _SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX, _MESH = (
    int(mujoco.mjtGeom.mjGEOM_PLANE),
    int(mujoco.mjtGeom.mjGEOM_SPHERE),
    int(mujoco.mjtGeom.mjGEOM_CAPSULE),
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID),
    int(mujoco.mjtGeom.mjGEOM_CYLINDER),
    int(mujoco.mjtGeom.mjGEOM_BOX),
    int(mujoco.mjtGeom.mjGEOM_MESH),
)
_SUPPORTED = (_PLANE, _SPHERE, _CAPSULE, _ELLIPSOID, _CYLINDER, _BOX, _MESH)
_EPS = 1e-4

# Each takes local origins/directions (..., 3) and sizes (..., 3) broadcastable to them and
# returns the ray parameter of the first hit in front of the origin, +inf on a miss.


def _first_root(b, a, c):
    """Smallest root > eps of a t^2 + 2 b t + c = 0, else inf."""
    disc = b * b - a * c
    safe_a = jnp.where(jnp.abs(a) > 1e-12, a, jnp.float32(1e-12))
    sq = jnp.sqrt(jnp.maximum(disc, 0.0))
    t = (-b - sq) / safe_a
    return jnp.where((disc >= 0) & (t > _EPS) & (jnp.abs(a) > 1e-12), t, jnp.inf)


def _hit_sphere(o, d, radius):
    return _first_root(jnp.sum(o * d, -1), jnp.sum(d * d, -1), jnp.sum(o * o, -1) - radius**2)


def _hit_ellipsoid(o, d, radii):
    o, d = o / radii, d / radii
    return _hit_sphere(o, d, jnp.float32(1.0))


def _hit_plane(o, d, size):
    dz = d[..., 2]
    safe = jnp.where(dz < -1e-12, dz, jnp.float32(-1e-12))
    t = -o[..., 2] / safe
    p = o + t[..., None] * d
    inside = ((size[..., 0] <= 0) | (jnp.abs(p[..., 0]) <= size[..., 0])) & (
        (size[..., 1] <= 0) | (jnp.abs(p[..., 1]) <= size[..., 1])
    )
    # Only the front side (+z) of a plane is drawn, as in MuJoCo.
    return jnp.where((dz < -1e-12) & (o[..., 2] > 0) & (t > _EPS) & inside, t, jnp.inf)


def _hit_box(o, d, half):
    inv_d = 1.0 / jnp.where(jnp.abs(d) > 1e-12, d, jnp.float32(1e-12))  # one division per axis, not two
    t1 = (-half - o) * inv_d
    t2 = (half - o) * inv_d
    t_near = jnp.max(jnp.minimum(t1, t2), -1)
    t_far = jnp.min(jnp.maximum(t1, t2), -1)
    return jnp.where((t_near <= t_far) & (t_near > _EPS), t_near, jnp.inf)


def _hit_tube(o, d, radius, half):
    """Side of a z-aligned cylinder of the given radius, |z| <= half."""
    o2, d2 = o[..., :2], d[..., :2]
    t = _first_root(jnp.sum(o2 * d2, -1), jnp.sum(d2 * d2, -1), jnp.sum(o2 * o2, -1) - radius**2)
    z = o[..., 2] + jnp.where(jnp.isfinite(t), t, 0.0) * d[..., 2]
    return jnp.where(jnp.abs(z) <= half, t, jnp.inf)


def _hit_capsule(o, d, size):
    radius, half = size[..., 0], size[..., 1]
    cap = jnp.stack([jnp.zeros_like(half), jnp.zeros_like(half), half], -1)
    return jnp.minimum(
        _hit_tube(o, d, radius, half),
        jnp.minimum(_hit_sphere(o - cap, d, radius), _hit_sphere(o + cap, d, radius)),
    )


def _hit_cylinder(o, d, size):
    radius, half = size[..., 0], size[..., 1]
    safe = jnp.where(jnp.abs(d[..., 2]) > 1e-12, d[..., 2], jnp.float32(1e-12))
    best = _hit_tube(o, d, radius, half)
    for sign in (-1.0, 1.0):
        t = (jnp.float32(sign) * half - o[..., 2]) / safe
        p = o + t[..., None] * d
        ok = (t > _EPS) & (jnp.sum(p[..., :2] ** 2, -1) <= radius**2)
        best = jnp.minimum(best, jnp.where(ok, t, jnp.inf))
    return best


_HIT = {
    _PLANE: _hit_plane,
    _SPHERE: lambda o, d, s: _hit_sphere(o, d, s[..., 0]),
    _CAPSULE: _hit_capsule,
    _ELLIPSOID: _hit_ellipsoid,
    _CYLINDER: _hit_cylinder,
    _BOX: _hit_box,
}


def _dot3(a, b):
    """Row-wise dot product of (..., 3) vectors, written per component: a ``sum(-1)`` over an axis of 3 is a
    reduction, which ends an XLA GPU fusion and writes its whole per-pixel input to memory."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _local_normal(gtype, p, size):
    """Outward unit normal at local hit points p (r, 3) of geoms of types gtype (r,), per component (no
    reductions, so the per-pixel shading stays one elementwise fusion on a GPU)."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    sx, sy, sz = (jnp.maximum(size[..., i], 1e-9) for i in range(3))
    zero = jnp.zeros_like(x)
    radius, half = size[..., 0], size[..., 1]
    on_cap = (jnp.abs(z) - half) > (jnp.sqrt(x * x + y * y) - radius)
    rx, ry, rz = jnp.abs(x) / sx, jnp.abs(y) / sy, jnp.abs(z) / sz
    along_x = (rx >= ry) & (rx >= rz)  # the box face's axis: the first largest, as argmax picks
    along_y = ~along_x & (ry >= rz)
    along_z = ~along_x & ~along_y
    candidates = {  # type -> (nx, ny, nz); anything else (a plane) faces +z
        _SPHERE: (x, y, z),
        _ELLIPSOID: (x / sx**2, y / sy**2, z / sz**2),
        _CAPSULE: (x, y, z - jnp.clip(z, -half, half)),
        _CYLINDER: (jnp.where(on_cap, zero, x), jnp.where(on_cap, zero, y), jnp.where(on_cap, jnp.sign(z), zero)),
        _BOX: (jnp.where(along_x, jnp.sign(x), zero), jnp.where(along_y, jnp.sign(y), zero),
               jnp.where(along_z, jnp.sign(z), zero)),
    }
    normal = (zero, zero, jnp.ones_like(x))
    for gt, candidate in candidates.items():
        normal = tuple(jnp.where(gtype == gt, c, n) for c, n in zip(candidate, normal))
    length = jnp.maximum(jnp.sqrt(normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2]), 1e-9)
    return jnp.stack([c / length for c in normal], -1)


def _rotate_rows(v, m):
    """``v @ m`` for row vectors v (..., 3) and a matrix m (3, 3) (or (..., 3, 3) matching v), written as
    three broadcast multiply-adds. A matrix product with a contraction of 3 would be a dot, which XLA's GPU
    backend emits as its own kernel writing its (rays, 3) result to memory; this stays elementwise and
    fuses into the intersection test that uses it."""
    return v[..., 0:1] * m[..., 0, :] + v[..., 1:2] * m[..., 1, :] + v[..., 2:3] * m[..., 2, :]


def hit_order(geom_type: np.ndarray) -> np.ndarray:
    """Drawn-geom indices in the order the renderer tests them (by type as in ``_HIT``, then index): a
    geom's position in it is its rank, and of equally near hits the lowest rank wins."""
    return np.concatenate([np.nonzero(geom_type == gtype)[0] for gtype in _HIT]).astype(np.int32)


def ranks_of_type(order: np.ndarray, geom_type: np.ndarray, gtype: int,
                  which: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ranks in ``order`` (:func:`hit_order`) of the drawn geoms of type ``gtype`` that ``which`` (bool (n,);
    ``None``: all) selects, and their drawn-geom indices: the geoms one type's test runs over."""
    ranks = np.nonzero(geom_type[order] == gtype)[0]
    if which is not None:
        ranks = ranks[which[order[ranks]]]
    return ranks, order[ranks]


@functools.lru_cache(maxsize=32)
def camera_dirs(fovy: float, height: int, width: int) -> np.ndarray:
    """One ray direction per pixel (R, 3) in the camera's frame (x right, y up, looking down -z), row 0
    at the top, with unit forward component so that the ray parameter t is the planar depth."""
    tan_half = np.tan(np.deg2rad(fovy) / 2.0)
    xs = ((np.arange(width) + 0.5) / width * 2.0 - 1.0) * tan_half * (width / height)
    ys = (1.0 - (np.arange(height) + 0.5) / height * 2.0) * tan_half
    grid_x, grid_y = np.meshgrid(xs, ys)  # (H, W)
    out = np.stack([grid_x, grid_y, -np.ones_like(grid_x)], -1).reshape(-1, 3).astype(np.float32)
    out.setflags(write=False)
    return out
