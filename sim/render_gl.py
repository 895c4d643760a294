"""MuJoCo's own OpenGL renderer (``mujoco.Renderer``, EGL/OSMesa) with the JAX renderer's outputs.

The reference the JAX renderer is tested against, and an optional fast RGB path for CPU data
generation on the C engine. It returns the same ``Frame`` fields as ``sim.render`` (numpy):
rgb uint8, depth in metres (planar, from MuJoCo's linearised depth buffer), geom_id (-1 for
background or non-geom objects) and seg (class ids of ``RenderScene.class_names``).
Only geoms are drawn: sites, joints, lights and frames are switched off in the visual
options so segmentation contains geoms alone, as in the JAX renderer.

Headless machines: with ``MUJOCO_GL`` unset, MuJoCo picks GLFW, which needs a display; on a
machine without one, a failed GLFW context followed by a second ``mujoco.Renderer`` aborts the
process (libc++abi "recursive initialization"). ``make_renderer`` therefore chooses the backend
once per process: the user's ``MUJOCO_GL`` or a display is respected as is; otherwise EGL, then
OSMesa, each probed in a subprocess (a broken GL stack cannot take this process down), and the
first that works is installed as MuJoCo's context class. A backend that failed once is never
tried again in this process; callers then fall back to the JAX renderer.
"""

from __future__ import annotations

import functools
import importlib
import os
import platform
import subprocess
import sys

import mujoco
import numpy as np

from sim.render import Frame, RenderScene

HEADLESS_BACKENDS = ("egl", "osmesa")
_PROBE = (
    "import mujoco\n"
    "m = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom size=\"1\"/></worldbody></mujoco>')\n"
    "r = mujoco.Renderer(m, 8, 8); r.render(); r.close()\n"
)


class GLUnavailableError(RuntimeError):
    """No OpenGL context can be made in this process (the message says why)."""


def _has_display() -> bool:
    if platform.system() != "Linux":
        return True  # macOS (CGL) and Windows (WGL) need no display variable
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _probe(backend: str) -> bool:
    env = {**os.environ, "MUJOCO_GL": backend}
    env.pop("PYOPENGL_PLATFORM", None)  # mujoco.<backend> sets the matching one
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.returncode == 0


def _install(backend: str) -> None:
    """Makes ``mujoco.Renderer`` create ``backend`` contexts, as ``MUJOCO_GL=backend`` at import would."""
    context_cls = importlib.import_module(f"mujoco.{backend}").GLContext
    # mujoco >= 3.4 keeps the selection in rendering.classic; older versions in mujoco.gl_context.
    for name in ("mujoco.rendering.classic.gl_context", "mujoco.gl_context"):
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        module.GLContext = context_cls
    os.environ["MUJOCO_GL"] = backend  # subprocesses and error messages see the same choice


@functools.cache
def gl_backend() -> str | None:
    """The OpenGL backend ``mujoco.Renderer`` uses in this process, or None when none works.

    Decided once per process. ``MUJOCO_GL`` set by the user, or a display, is taken as is
    (``"glfw"`` stands for MuJoCo's default); a headless machine gets EGL, else OSMesa.
    """
    requested = os.environ.get("MUJOCO_GL", "").strip().lower()
    if requested or _has_display():
        return requested or "glfw"
    for backend in HEADLESS_BACKENDS:
        if _probe(backend):
            try:
                _install(backend)
            except Exception:  # noqa: BLE001 - e.g. PyOpenGL already loaded for another platform
                continue
            return backend
    return None


_failure: list[str] = []  # the first context failure of this process; retrying it can abort


def make_renderer(model: mujoco.MjModel, height: int, width: int) -> mujoco.Renderer:
    """``mujoco.Renderer(model, height, width)`` on the backend ``gl_backend`` chose.

    Raises:
      GLUnavailableError: no backend works here, or an earlier context failed in this process.
    """
    if _failure:
        raise GLUnavailableError(_failure[0])
    backend = gl_backend()
    if backend is None:
        _failure.append(f"no display and no headless OpenGL ({' or '.join(HEADLESS_BACKENDS)}) works here; "
                        "set MUJOCO_GL to a working backend")
        raise GLUnavailableError(_failure[0])
    try:
        return mujoco.Renderer(model, height, width)
    except Exception as err:  # noqa: BLE001 - any GL failure means "not available"
        _failure.append(f"mujoco.Renderer cannot open a context with MUJOCO_GL={backend}: {err}")
        raise GLUnavailableError(_failure[0]) from err


def gl_available() -> tuple[bool, str]:
    """(True, "") if an offscreen OpenGL context can be made, else (False, the reason)."""
    try:
        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>")
        make_renderer(model, 8, 8).close()
        return True, ""
    except GLUnavailableError as err:
        return False, str(err)


class GLRenderer:
    """``mujoco.Renderer`` for one camera, returning a numpy ``Frame``.

    Args:
      model: the compiled model (its ``vis.global.offwidth/offheight`` must cover the size).
      scene: the JAX renderer's scene, for the geom groups' class map and the far depth.
      camera: camera name. height, width: image size. shadows: MuJoCo's shadow mapping.
      geomgroups: geom groups drawn (match ``build_scene``'s).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        scene: RenderScene,
        camera: str,
        *,
        height: int,
        width: int,
        shadows: bool = False,
        geomgroups: tuple[int, ...] = (0, 1, 2),
    ):
        if camera not in scene.cameras:
            raise KeyError(f"camera {camera!r} not in the model; cameras: {sorted(scene.cameras)}")
        if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
            model.vis.global_.offwidth = max(width, model.vis.global_.offwidth)
            model.vis.global_.offheight = max(height, model.vis.global_.offheight)
        self._model, self._scene, self._camera = model, scene, camera
        self._renderer = make_renderer(model, height, width)
        self._option = mujoco.MjvOption()
        self._option.geomgroup[:] = [int(g in geomgroups) for g in range(len(self._option.geomgroup))]
        self._option.sitegroup[:] = 0
        self._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(shadows)

    def close(self) -> None:
        self._renderer.close()

    def __enter__(self) -> "GLRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def render(self, data: mujoco.MjData, *, rgb_only: bool = False) -> Frame:
        """Renders ``data`` (after ``mj_forward``/``mj_step``)."""
        r = self._renderer
        r.update_scene(data, self._camera, self._option)
        rgb = r.render().copy()
        if rgb_only:
            return Frame(rgb=rgb, depth=None, geom_id=None, seg=None)
        r.enable_depth_rendering()
        depth = r.render().astype(np.float32)
        r.disable_depth_rendering()
        r.enable_segmentation_rendering()
        ids = r.render()
        r.disable_segmentation_rendering()
        is_geom = ids[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)
        geom_id = np.where(is_geom, ids[..., 0], -1).astype(np.int32)
        seg = np.where(geom_id >= 0, self._scene.geom_class[np.maximum(geom_id, 0)], 0).astype(np.int32)
        far = self._model.vis.map.zfar * self._model.stat.extent
        depth = np.where((geom_id < 0) | (depth >= far * 0.999), np.float32(self._scene.far), depth)
        return Frame(rgb=rgb, depth=depth.astype(np.float32), geom_id=geom_id, seg=seg)
