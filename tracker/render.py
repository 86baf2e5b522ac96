"""Offscreen rendering of object meshes at poses (pyrender, EGL), one persistent renderer.

Create a :class:`Renderer` once and reuse it: building the GL context and uploading the
meshes costs far more than a frame. Poses are BOP model-to-camera transforms (OpenCV
camera: x right, y down, z forward), translations in mm.
"""
from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

from .errors import UserError  # noqa: E402

# OpenCV camera -> OpenGL camera (y up, looking down -z)
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
# far behind the camera: clipped away without leaving the scene
_PARKED = np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -1e7], [0, 0, 0, 1]])


def _pyrender():
    try:
        import pyrender
    except Exception as e:  # missing EGL / GL libraries surface here
        raise UserError(f"cannot start the offscreen renderer ({e.__class__.__name__}: {e}); "
                        f"it needs EGL (Mesa) with PYOPENGL_PLATFORM=egl") from None
    return pyrender


def pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
    return T


class Renderer:
    """Renders any subset of the given object meshes at given poses.

    ``meshes``: {obj_id: trimesh.Trimesh} in mm. Lighting: ambient plus a head light
    (a directional light along the viewing direction), both adjustable per call.
    """

    def __init__(self, width: int, height: int, meshes: dict, znear: float = 10.0,
                 zfar: float = 10000.0, ambient: float = 0.45, headlight: float = 2.5):
        pr = _pyrender()
        self.pr = pr
        self.width, self.height = int(width), int(height)
        self.znear, self.zfar = znear, zfar
        try:
            self._r = pr.OffscreenRenderer(self.width, self.height)
        except Exception as e:
            raise UserError(f"cannot create an offscreen GL context ({e.__class__.__name__}: {e}); "
                            f"set PYOPENGL_PLATFORM=egl and check Mesa's EGL is installed") from None
        self.scene = pr.Scene(bg_color=np.zeros(4), ambient_light=np.full(3, ambient))
        self._meshes = {int(k): pr.Mesh.from_trimesh(m, smooth=True) for k, m in meshes.items()}
        # Nodes stay in the scene for the renderer's life: removing a mesh from the scene
        # makes pyrender free its GPU buffers and upload them again when it comes back.
        # Unused meshes are hidden, unused extra instances parked behind the camera.
        self._pool: dict[int, list] = {k: [] for k in self._meshes}
        self._cam = pr.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=znear, zfar=zfar)
        self._cam_node = self.scene.add(self._cam, pose=_CV_TO_GL)
        self._light = pr.DirectionalLight(color=np.ones(3), intensity=headlight)
        self._light_node = self.scene.add(self._light, pose=_CV_TO_GL)

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self._meshes)

    def set_camera(self, K: np.ndarray) -> None:
        K = np.asarray(K, dtype=np.float64)
        # pyrender puts the principal point on pixel edges; OpenCV on pixel centres
        self._cam.fx, self._cam.fy = K[0, 0], K[1, 1]
        self._cam.cx, self._cam.cy = K[0, 2] + 0.5, K[1, 2] + 0.5

    def render(self, K: np.ndarray, instances, ambient: float | None = None,
               headlight: float | None = None, depth_only: bool = False):
        """Render ``instances`` = [(obj_id, R, t), ...]; returns (rgb uint8 HxWx3, depth mm HxW).

        ``depth`` is 0 where no object is. With ``depth_only`` rgb is None.
        """
        pr = self.pr
        self.set_camera(K)
        if ambient is not None:
            self.scene.ambient_light = np.full(3, ambient)
        if headlight is not None:
            self._light.intensity = headlight
        self._place(instances)
        if depth_only:
            return None, self._r.render(self.scene, flags=pr.RenderFlags.DEPTH_ONLY)
        rgb, depth = self._r.render(self.scene)
        return rgb, depth

    def _place(self, instances) -> None:
        used = {k: 0 for k in self._meshes}
        for obj_id, R, t in instances:
            k = int(obj_id)
            if k not in self._meshes:
                raise UserError(f"no mesh for object {obj_id} in the renderer (has {self.obj_ids})")
            pool = self._pool[k]
            if used[k] == len(pool):
                pool.append(self.scene.add(self._meshes[k], pose=_PARKED))
            self.scene.set_pose(pool[used[k]], pose_matrix(R, t))
            used[k] += 1
        for k, mesh in self._meshes.items():
            mesh.is_visible = used[k] > 0
            for node in self._pool[k][used[k]:]:
                self.scene.set_pose(node, _PARKED)

    def close(self) -> None:
        if self._r is not None:
            self._r.delete()
            self._r = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
