"""Offscreen rendering of object meshes at poses (pyrender, EGL), one persistent renderer.

Create a :class:`Renderer` once and reuse it: building the GL context and uploading the
meshes costs far more than a frame. Poses are BOP model-to-camera transforms (OpenCV
camera: x right, y down, z forward), translations in mm.
"""
from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

from tracker.core.errors import UserError  # noqa: E402

# OpenCV camera -> OpenGL camera (y up, looking down -z)
_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])
# far behind the camera: clipped away without leaving the scene
_PARKED = np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -1e7], [0, 0, 0, 1]])


# pyrender always draws into a 4x multisampled framebuffer; on Mesa's llvmpipe (the CPU
# rasteriser here) that costs 2.5x (measured: 8 LM-O objects at 640x480, 281 -> 115 ms RGB,
# 93 -> 42 ms depth). Off by default; AUTOPOSE_MSAA=4 brings it back.
MSAA_SAMPLES = int(os.environ.get("AUTOPOSE_MSAA", "0"))


def _pyrender():
    try:
        import pyrender
        import pyrender.renderer as prr
        from OpenGL import GL
    except Exception as e:  # missing EGL / GL libraries surface here
        raise UserError(f"cannot start the offscreen renderer ({e.__class__.__name__}: {e}); "
                        f"it needs EGL (Mesa) with PYOPENGL_PLATFORM=egl") from None
    if not getattr(prr, "_autopose_patched", False):
        prr.glRenderbufferStorageMultisample = (
            lambda target, samples, fmt, w, h: GL.glRenderbufferStorageMultisample(target, MSAA_SAMPLES, fmt, w, h))
        # pyrender sizes its shader's light arrays for 4 lights of each kind; llvmpipe pays for
        # the spot and point light loops even when they run 0 times. Our renderers use only
        # directional lights (at most MAX_LIGHTS), so the others get one slot each: the same
        # images, the 640x480 scene render ~40 % faster on this CPU.
        compute = prr.Renderer._compute_max_n_lights
        prr.Renderer._compute_max_n_lights = (
            lambda self, flags: [min(n, cap) for n, cap in zip(compute(self, flags), (MAX_LIGHTS, 1, 1))])
        prr._autopose_patched = True
    return pyrender


MAX_LIGHTS = 4
_CONTEXTS = [0]  # GL contexts this process has made (a fork after one hangs: synth checks)


def contexts_made() -> int:
    return _CONTEXTS[0]



def _light_pose(direction_cv: np.ndarray) -> np.ndarray:
    """Pose (in the OpenCV camera frame used as world) of a directional light shining
    along ``direction_cv``; pyrender lights shine along their local -z."""
    d = direction_cv / np.linalg.norm(direction_cv)
    z = -d
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    return T


METALLIC, ROUGHNESS = 0.0, 0.8  # the objects' default material: matte, not metallic


def pose_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
    return T


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB values in [0, 1] -> linear light (the colours pyrender shades with)."""
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _to_pyrender(pr, mesh):
    """A pyrender mesh whose vertex colours are linear.

    pyrender multiplies vertex colours into its linear shading and then gamma-encodes the
    result (pow 1/2.2), so sRGB colours passed as they are come out washed out (LM-O's ape,
    stored as (148, 57, 57), rendered at about (190, 125, 120)). Linearising them first
    gives back the stored colours under white light of unit intensity.
    """
    visual = getattr(mesh, "visual", None)
    if getattr(visual, "kind", None) != "vertex":
        return pr.Mesh.from_trimesh(mesh, smooth=True)
    srgb = np.asarray(visual.vertex_colors, dtype=np.float32)[:, :3] / 255.0
    linear = srgb_to_linear(srgb)
    colours = np.concatenate([linear, np.ones((len(linear), 1), np.float32)], axis=1)
    material = pr.MetallicRoughnessMaterial(baseColorFactor=np.ones(4), metallicFactor=METALLIC, roughnessFactor=ROUGHNESS)
    prim = pr.Primitive(positions=np.asarray(mesh.vertices, dtype=np.float32),
                        normals=np.asarray(mesh.vertex_normals, dtype=np.float32),
                        indices=np.asarray(mesh.faces, dtype=np.uint32), color_0=colours, material=material)
    return pr.Mesh(primitives=[prim])


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
        _CONTEXTS[0] += 1
        self.scene = pr.Scene(bg_color=np.zeros(4), ambient_light=np.full(3, ambient))
        self._meshes = {int(k): _to_pyrender(pr, m) for k, m in meshes.items()}
        # Nodes stay in the scene for the renderer's life: removing a mesh from the scene
        # makes pyrender free its GPU buffers and upload them again when it comes back.
        # Unused meshes are hidden, unused extra instances parked behind the camera.
        self._pool: dict[int, list] = {k: [] for k in self._meshes}
        self._cam = pr.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=znear, zfar=zfar)
        self._cam_node = self.scene.add(self._cam, pose=_CV_TO_GL)
        # a fixed set of directional lights (the first is the head light); set_lights
        # changes their directions, colours and intensities without touching the scene graph
        self._lights = [pr.DirectionalLight(color=np.ones(3), intensity=headlight if i == 0 else 0.0)
                        for i in range(MAX_LIGHTS)]
        self._light_nodes = [self.scene.add(light, pose=_CV_TO_GL) for light in self._lights]

    @property
    def obj_ids(self) -> list[int]:
        return sorted(self._meshes)

    def set_lights(self, lights) -> None:
        """``lights``: [(direction in camera coordinates (x right, y down, z forward),
        RGB colour in 0..1, intensity), ...], at most MAX_LIGHTS; the rest are switched off."""
        lights = list(lights)
        if len(lights) > MAX_LIGHTS:
            raise ValueError(f"at most {MAX_LIGHTS} lights")
        for i, (light, node) in enumerate(zip(self._lights, self._light_nodes)):
            if i >= len(lights):
                light.intensity = 0.0
                continue
            d, c, inten = lights[i]
            light.color = np.asarray(c, dtype=np.float64)
            light.intensity = float(inten)
            self.scene.set_pose(node, _light_pose(np.asarray(d, dtype=np.float64)))

    def set_ambient(self, ambient) -> None:
        self.scene.ambient_light = np.broadcast_to(np.asarray(ambient, dtype=np.float64), (3,)).copy()

    def set_material(self, obj_id: int, metallic: float = METALLIC, roughness: float = ROUGHNESS,
                     colour=(1.0, 1.0, 1.0)) -> None:
        """Make an object glossier, more metallic or tinted (``colour``: linear RGB factor on its
        vertex colours) for the following renders (every instance of it); the defaults give back
        the matte, untinted material. pyrender reads the factors at each draw."""
        if int(obj_id) not in self._meshes:
            raise UserError(f"no mesh for object {obj_id} in the renderer (has {self.obj_ids})")
        for prim in self._meshes[int(obj_id)].primitives:
            if prim.material is not None:
                prim.material.metallicFactor = float(metallic)
                prim.material.roughnessFactor = float(roughness)
                prim.material.baseColorFactor = np.append(np.asarray(colour, np.float64).ravel()[:3], 1.0)

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
            self.set_ambient(ambient)
        if headlight is not None:
            self.set_lights([((0.0, 0.0, 1.0), (1.0, 1.0, 1.0), headlight)])
        self._place(instances)
        if depth_only:
            return None, self._r.render(self.scene, flags=pr.RenderFlags.DEPTH_ONLY)
        rgb, depth = self._r.render(self.scene)
        return rgb, depth

    def render_labels(self, K: np.ndarray, instances) -> np.ndarray:
        """Which instance is in front at each pixel: int32 HxW, the index into ``instances``,
        -1 where none is (one flat-shaded pass, no lighting)."""
        pr = self.pr
        self.set_camera(K)
        nodes = self._place(instances)
        if len(instances) >= 255 ** 2:
            raise ValueError("too many instances for the label encoding")
        seg = {n: np.array([(i + 1) % 255, (i + 1) // 255, 0], dtype=np.uint8) for i, n in enumerate(nodes)}
        col, _ = self._r.render(self.scene, flags=pr.RenderFlags.SEG, seg_node_map=seg)
        return col[..., 0].astype(np.int32) + 255 * col[..., 1].astype(np.int32) - 1

    def _place(self, instances) -> list:
        """Pose the pooled nodes for ``instances``; returns their nodes in order."""
        nodes = []
        used = {k: 0 for k in self._meshes}
        for obj_id, R, t in instances:
            k = int(obj_id)
            if k not in self._meshes:
                raise UserError(f"no mesh for object {obj_id} in the renderer (has {self.obj_ids})")
            pool = self._pool[k]
            if used[k] == len(pool):
                pool.append(self.scene.add(self._meshes[k], pose=_PARKED))
            self.scene.set_pose(pool[used[k]], pose_matrix(R, t))
            nodes.append(pool[used[k]])
            used[k] += 1
        for k, mesh in self._meshes.items():
            mesh.is_visible = used[k] > 0
            for node in self._pool[k][used[k]:]:
                self.scene.set_pose(node, _PARKED)
        return nodes

    def close(self) -> None:
        if self._r is not None:
            try:
                self._r.delete()
            except Exception:  # pyrender terminates the shared EGL display with the first renderer
                pass
            self._r = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
