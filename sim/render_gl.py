"""MuJoCo's own OpenGL renderer (``mujoco.Renderer``, EGL/OSMesa) with the JAX renderer's outputs.

The reference the JAX renderer is tested against, and an optional fast RGB path for CPU data
generation on the C engine. It returns the same ``Frame`` fields as ``sim.render`` (numpy):
rgb uint8, depth in metres (planar, from MuJoCo's linearised depth buffer), geom_id (-1 for
background or non-geom objects) and seg (class ids of ``RenderScene.class_names``).
Only geoms are drawn: sites, joints, lights and frames are switched off in the visual
options so segmentation contains geoms alone, as in the JAX renderer.
"""

from __future__ import annotations

import os

import mujoco
import numpy as np

from sim.render import Frame, RenderScene


def gl_available() -> tuple[bool, str]:
    """(True, "") if an offscreen OpenGL context can be made, else (False, the reason)."""
    try:
        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>")
        renderer = mujoco.Renderer(model, 8, 8)
        renderer.close()
        return True, ""
    except Exception as err:  # noqa: BLE001 - any GL failure means "not available"
        backend = os.environ.get("MUJOCO_GL", "(unset)")
        return False, f"mujoco.Renderer cannot open a context with MUJOCO_GL={backend}: {err}"


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
        self._renderer = mujoco.Renderer(model, height, width)
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
