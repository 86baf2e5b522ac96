"""Domain randomisation: backgrounds, distractor meshes, lights and camera effects.

Every function takes the generator it draws from, so a scene is a pure function of its seed.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import trimesh

from tracker.core.errors import UserError
from tracker.core.files import require_utf8
from tracker.core.geometry import project
from tracker.core.meshes import read_mesh
from tracker.core.visibility import mask_box
from tracker.runtime.render import srgb_to_linear

BG_EXTS = (".jpg", ".jpeg", ".png")


# --------------------------------------------------------------------------- backgrounds


def list_backgrounds(folder) -> list[Path]:
    d = Path(folder)
    if not d.is_dir():
        raise UserError(f"backgrounds folder not found: {d}")
    # a file that is not an image (by its signature) is skipped; one that is cut short is
    # refused when first drawn (Backgrounds.photo)
    files = sorted(require_utf8(p, "background") for p in d.iterdir() if p.suffix.lower() in BG_EXTS)
    files = [p for p in files if cv2.haveImageReader(str(p))]
    if not files:
        raise UserError(f"{d}: no readable .jpg/.png background images")
    return files


class Backgrounds:
    """Photos (decoded when first drawn, then kept small) and procedural textures, as RGB
    uint8 frames. Decoding all 47 photos of the shared set took 0.36 s of each worker's
    start; a short split draws only some of them."""

    def __init__(self, files: list[Path], p_procedural: float = 0.25):
        self.files = list(files)
        if not self.files:
            raise UserError("no background image")
        self._decoded: dict[int, np.ndarray] = {}
        self.p_procedural = p_procedural

    def photo(self, i: int) -> np.ndarray:
        if i not in self._decoded:
            bgr = cv2.imread(str(self.files[i]), cv2.IMREAD_COLOR)
            if bgr is None:
                raise UserError(f"unreadable background image: {self.files[i]} (remove it from the folder)")
            s = 800.0 / max(bgr.shape[:2])
            if s < 1:
                bgr = cv2.resize(bgr, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            self._decoded[i] = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        return self._decoded[i]

    @property
    def images(self) -> list[np.ndarray]:
        """All photos, decoded."""
        return [self.photo(i) for i in range(len(self.files))]

    def sample(self, rng: np.random.Generator, width: int, height: int) -> np.ndarray:
        if rng.random() < self.p_procedural:
            return procedural_texture(rng, width, height)
        img = self.photo(int(rng.integers(len(self.files))))
        h, w = img.shape[:2]
        # random scale, crop, flip
        s = max(width / w, height / h) * rng.uniform(1.0, 1.8)
        big = cv2.resize(img, (max(width, int(w * s + 1)), max(height, int(h * s + 1))), interpolation=cv2.INTER_LINEAR)
        y0 = rng.integers(0, big.shape[0] - height + 1)
        x0 = rng.integers(0, big.shape[1] - width + 1)
        out = big[y0:y0 + height, x0:x0 + width]
        if rng.random() < 0.5:
            out = out[:, ::-1]
        return np.ascontiguousarray(out)


def procedural_texture(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """Smooth colour noise, stripes, checkers or a gradient."""
    kind = rng.integers(4)
    if kind == 0:  # multi-scale colour noise
        out = np.zeros((height, width, 3), np.float32)
        for cells in (4, 16, 64):
            n = rng.uniform(0, 1, (max(2, height * cells // width), cells, 3)).astype(np.float32)
            out += cv2.resize(n, (width, height), interpolation=cv2.INTER_CUBIC) / 3
        img = out
    elif kind == 1:  # stripes
        period = rng.uniform(8, 80)
        ang = rng.uniform(0, np.pi)
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
        s = (np.sin((xx * np.cos(ang) + yy * np.sin(ang)) * 2 * np.pi / period) > 0)[..., None]
        img = np.where(s, rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)).astype(np.float32)
    elif kind == 2:  # checkers
        c = int(rng.integers(10, 80))
        yy, xx = np.mgrid[0:height, 0:width]
        s = (((xx // c) + (yy // c)) % 2 == 0)[..., None]
        img = np.where(s, rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)).astype(np.float32)
    else:  # gradient
        a, b = rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)
        g = np.linspace(0, 1, width, dtype=np.float32)[None, :, None]
        img = np.broadcast_to(a + (b - a) * g, (height, width, 3)).astype(np.float32)
    return np.clip(img * 255, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- the table


def table_surface(texture: np.ndarray, K: np.ndarray, R_w2c: np.ndarray, t_w2c: np.ndarray,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The table top seen by the camera: ``texture`` (RGB) laid on the plane world z = 0,
    tiled (mirrored) at a random scale and turn, ending at a random table edge 0.5-1.5 m from
    the centre; returns (image, mask) at the texture's size. Beyond the edge and above the
    horizon the mask is False (the photo behind shows there)."""
    h, w = texture.shape[:2]
    # pixel -> plane is the homography (K [r1 r2 t])^-1: q = (X, Y, 1) / depth, so q3 > 0
    # in front of the camera, and every test and map below is linear in (u, v) until the
    # division (float32 planes: this is the costliest part of a synthetic image otherwise)
    Hinv = np.linalg.inv(np.asarray(K, np.float64) @ np.column_stack([R_w2c[:, 0], R_w2c[:, 1], t_w2c]))
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    q1, q2, q3 = (np.float32(a) * u + np.float32(b) * v + np.float32(c) for a, b, c in Hinv)
    half = rng.uniform(500, 1500, 2)
    mask = (q3 > 0) & (np.abs(q1) < np.float32(half[0]) * q3) & (np.abs(q2) < np.float32(half[1]) * q3)
    mm_per_px = rng.uniform(400, 1500) / w  # the texture spans 0.4-1.5 m before it repeats
    a = rng.uniform(0, 2 * np.pi)
    ca, sa = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(mask, np.float32(1.0 / mm_per_px) / q3, np.float32(0))
    mx = np.where(mask, (np.float32(ca) * q1 - np.float32(sa) * q2) * inv + np.float32(w / 2), np.float32(-1))
    my = np.where(mask, (np.float32(sa) * q1 + np.float32(ca) * q2) * inv + np.float32(h / 2), np.float32(-1))
    img = cv2.remap(texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    # light falls off across the table, as under a lamp
    shade = (1.0 + rng.uniform(-0.25, 0.25) * (u - w / 2) / w + rng.uniform(-0.25, 0.25) * (v - h / 2) / h)
    shade = shade.astype(np.float32)
    img = cv2.multiply(img, cv2.merge([shade] * img.shape[2]), dtype=cv2.CV_8U)  # (rounded, saturated)
    return img, mask


def cast_shadows(img: np.ndarray, world_vertices: list[np.ndarray], light_dir_w: np.ndarray, K: np.ndarray,
                 R_w2c: np.ndarray, t_w2c: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Soft shadows of objects standing on the table: each object's vertices (world, mm)
    pushed along the light's direction down to z = 0, their outline filled, blurred and
    darkening ``img`` (the table, before the objects are composited over it)."""
    d = np.asarray(light_dir_w, np.float64)
    d = d / np.linalg.norm(d)
    if d[2] > -0.35:  # a grazing or upward light: shadows mostly straight down (contact shadows)
        d = np.array([d[0], d[1], 0.0]) * 0.5 + np.array([0.0, 0.0, -1.0])
    shadow = np.zeros(img.shape[:2], np.float32)
    for V in world_vertices:  # (the engine passes about 400 of each object's vertices)
        P = V - (V[:, 2:3] / d[2]) * d  # along d down to the table
        if np.any((P @ R_w2c.T + t_w2c)[:, 2] <= 1.0):  # partly behind the camera
            continue
        uv = project(P, K, R_w2c, t_w2c)
        if np.abs(uv).max() > 1e5:
            continue
        hull = cv2.convexHull(np.round(uv).astype(np.int32))
        cv2.fillConvexPoly(shadow, hull, 1.0, lineType=cv2.LINE_AA)
    if not shadow.any():
        return img
    shadow = cv2.GaussianBlur(shadow, (0, 0), rng.uniform(2.0, 8.0))
    dark = 1.0 - rng.uniform(0.3, 0.65) * np.clip(shadow, 0, 1)
    return (img * dark[..., None]).astype(np.uint8)


# --------------------------------------------------------------------------- distractors


def distractor_meshes(rng: np.random.Generator, n: int = 12) -> list[trimesh.Trimesh]:
    """Primitives 30-200 mm with noisy vertex colours (a cheap random texture)."""
    makers = [
        lambda s: trimesh.creation.box(extents=s * rng.uniform(0.3, 1.0, 3)),
        lambda s: trimesh.creation.cylinder(radius=s * rng.uniform(0.15, 0.5), height=s, sections=24),
        lambda s: trimesh.creation.icosphere(subdivisions=2, radius=s / 2),
        lambda s: trimesh.creation.capsule(height=s, radius=s * rng.uniform(0.1, 0.3)),
        lambda s: trimesh.creation.cone(radius=s * rng.uniform(0.2, 0.5), height=s, sections=24),
        lambda s: trimesh.creation.torus(major_radius=s * 0.35, minor_radius=s * rng.uniform(0.05, 0.15)),
    ]
    out = []
    for i in range(n):
        m = makers[i % len(makers)](rng.uniform(30, 200))
        m = m.subdivide() if len(m.vertices) < 200 else m
        base = rng.uniform(0, 255, 3)
        noise = rng.normal(0, rng.uniform(5, 60), (len(m.vertices), 3))
        cols = np.clip(base + noise, 0, 255).astype(np.uint8)
        m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=np.concatenate([cols, np.full((len(cols), 1), 255, np.uint8)], 1))
        out.append(m)
    return out


def household_meshes(rng: np.random.Generator, n: int = 18) -> list[trimesh.Trimesh]:
    """Upright (z up) mugs with handles, cups wider at the top and bottles with a neck: the
    real clutter the detector mistook for targets on the dev frames (a blue mug for the
    holepuncher, a yellow cup for the duck, a bottle for the can). Grey until textured."""
    def mug():
        r, h = rng.uniform(35, 48), rng.uniform(80, 115)
        body = trimesh.creation.cylinder(radius=r, height=h, sections=32)
        handle = trimesh.creation.torus(major_radius=0.3 * h, minor_radius=rng.uniform(5, 9),
                                        major_sections=24, minor_sections=8)
        handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        handle.apply_translation([r, 0, 0])
        return trimesh.util.concatenate([body, handle])

    def cup():
        rb, h = rng.uniform(25, 35), rng.uniform(80, 120)
        return trimesh.creation.revolve([[0, 0], [rb, 0], [rb * rng.uniform(1.2, 1.5), h], [0, h]], sections=32)

    def bottle():
        r, h, rn = rng.uniform(28, 45), rng.uniform(150, 260), rng.uniform(11, 18)
        return trimesh.creation.revolve([[0, 0], [r, 0], [r, 0.6 * h], [rn, 0.8 * h], [rn, h], [0, h]], sections=32)

    makers = [mug, cup, bottle]
    out = []
    for i in range(n):
        m = makers[i % len(makers)]()
        m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=np.full((len(m.vertices), 4), 200, np.uint8))
        out.append(m.subdivide() if len(m.vertices) < 400 else m)
    return out


MESH_EXTS = (".ply", ".obj", ".glb", ".stl")


def list_occluders(folder) -> list[Path]:
    """The mesh files of an occluder folder (``synth --occluders``), sorted."""
    d = Path(folder)
    if not d.is_dir():
        raise UserError(f"occluders folder not found: {d}")
    files = sorted(p for p in d.iterdir() if p.suffix.lower() in MESH_EXTS)
    if not files:
        raise UserError(f"{d}: no .ply/.obj/.glb/.stl meshes (scripts/debian_assets.py furniture makes some)")
    return files


def vertex_coloured(m: trimesh.Trimesh) -> trimesh.Trimesh:
    """``m`` (in place) with vertex colours, as the renderer colours: its own, its face colours,
    its texture sampled at the vertices' UVs, its material's colour, else grey."""
    if m.visual.kind == "vertex":
        return m
    try:
        colours = np.asarray((m.visual if m.visual.kind == "face" else m.visual.to_color()).vertex_colors, np.uint8)
    except Exception:  # noqa: BLE001 - no UVs or no image: no sampled colour
        colours = np.empty((0, 4), np.uint8)
    if colours.ndim != 2 or len(colours) != len(m.vertices):
        main = getattr(getattr(m.visual, "material", None), "main_color", None)
        colours = np.tile(np.asarray(main if main is not None else (180, 180, 180, 255), np.uint8),
                          (len(m.vertices), 1))
    m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=colours)
    return m


def occluder_meshes(files: list[Path], rng: np.random.Generator, n: int = 48,
                    size_mm: tuple[float, float] = (40.0, 250.0)) -> list[trimesh.Trimesh]:
    """``n`` of the meshes (all, if fewer), each centred and scaled to a largest side drawn
    from ``size_mm`` (household things on a table), in their own vertex colours (grey where a
    file has none). A file that is not a mesh is one error naming it."""
    pick = rng.permutation(len(files))[:n]
    out = []
    for i in sorted(int(k) for k in pick):
        m = read_mesh(files[i])  # checked: triangles, finite vertices, an area
        vertex_coloured(m)
        m.apply_translation(-m.bounds.mean(0))
        m.apply_scale(rng.uniform(*size_mm) / max(float(m.extents.max()), 1e-9))
        out.append(m)
    return out


def texture_from_photos(meshes: list[trimesh.Trimesh], photos: list[np.ndarray], rng: np.random.Generator) -> None:
    """Replace each mesh's vertex colours by a patch of a photo projected along a random axis,
    brightened towards white: printed boxes, mugs, cables and books rather than flat primitives.
    ``tint_distractors`` then colours them per image."""
    for m in meshes:
        photo = photos[int(rng.integers(len(photos)))]
        h, w = photo.shape[:2]
        lo = min(48, h, w)  # a photo smaller than 48 px gives a patch of its size
        side = int(rng.integers(lo, max(lo + 1, min(h, w, 320))))
        y0, x0 = int(rng.integers(0, h - side + 1)), int(rng.integers(0, w - side + 1))
        patch = photo[y0:y0 + side, x0:x0 + side].astype(np.float32)
        axes = np.linalg.qr(rng.normal(size=(3, 3)))[0][:, :2]
        uv = np.asarray(m.vertices) @ axes
        uv = (uv - uv.min(0)) / max(float(np.ptp(uv, axis=0).max()), 1e-6) * (side - 1)
        cols = patch[uv[:, 1].astype(int), uv[:, 0].astype(int)]
        cols = 255 - (255 - cols) * rng.uniform(0.3, 0.8)  # lighter: the tint sets the colour
        rgba = np.concatenate([np.clip(cols, 0, 255), np.full((len(cols), 1), 255)], 1).astype(np.uint8)
        m.visual = trimesh.visual.ColorVisuals(m, vertex_colors=rgba)


def target_palette(meshes: list[trimesh.Trimesh], rng: np.random.Generator, per_mesh: int = 16) -> np.ndarray:
    """(N, 3) sRGB colours in [0, 1] drawn from the targets' vertex colours: distractors tinted
    with them (a yellow cup, a white box, a blue mug) teach the detector that colour alone is
    not an object."""
    out = []
    for m in meshes:
        vc = np.asarray(getattr(m.visual, "vertex_colors", np.zeros((0, 4))))[:, :3]
        if len(vc):
            out.append(vc[rng.integers(0, len(vc), per_mesh)] / 255.0)
    return np.concatenate(out) if out else np.ones((1, 3))


def tint_distractors(renderer, dis_ids, palette: np.ndarray, rng: np.random.Generator,
                     p_palette: float = 0.5) -> None:
    """A base colour per distractor mesh for the next renders: a target's colour (with p_palette),
    else a random one; glossy now and then."""
    for did in dis_ids:
        if rng.random() < p_palette:
            c = np.clip(palette[int(rng.integers(len(palette)))] + rng.normal(0, 0.06, 3), 0, 1)
        else:
            c = rng.uniform(0, 1, 3)
        lin = srgb_to_linear(c)  # the renderer's vertex colours are linear too
        glossy = rng.random() < 0.3
        renderer.set_material(did, metallic=rng.uniform(0, 0.3) if glossy else 0.0,
                              roughness=rng.uniform(0.2, 0.6) if glossy else 0.8, colour=lin)


# --------------------------------------------------------------------------- lights


def _from_camera_side(rng: np.random.Generator, lift: float) -> np.ndarray:
    """A random light direction shining away from the camera, onto the scene (z >= ``lift``)."""
    d = rng.normal(size=3)
    d[2] = abs(d[2]) + lift
    return d


def sample_lights(rng: np.random.Generator):
    """1-3 directional lights from the camera's side of the scene, random colour and
    intensity, plus an ambient level. Returns (lights, ambient RGB).

    Levels were set against the LM-O dev frames (crop colour statistics): with ambient
    0.15-0.6 and lights 1-4.5 the objects came out 1.7x brighter than the camera shows them
    (most of it was pyrender's gamma on vertex colours, fixed in render.py)."""
    lights = []
    for i in range(int(rng.integers(1, 4))):
        d = _from_camera_side(rng, 0.3)
        colour = 1.0 - rng.uniform(0, 0.25, 3)
        lights.append((d, colour, rng.uniform(0.5, 2.0) / (1 + 0.5 * i)))
    ambient = rng.uniform(0.15, 0.5) * (1.0 - rng.uniform(0, 0.15, 3))
    return lights, ambient


def sample_overhead_lights(rng: np.random.Generator, down_c: np.ndarray):
    """A room lit from the ceiling: one strong key light shining down onto the table (``down_c``,
    the table's downward normal in the camera frame, plus Gaussian noise of 0.2 per axis: a
    median 13 degrees off it, 95 % within 29), most of the time a weak fill from the camera's
    side, and a low ambient level. Returns (lights, ambient RGB), key light first (the
    table's shadows follow it).

    The real LM-O objects show bright tops, dark sides and highlights; the lights of
    :func:`sample_lights`, from the camera's side of the scene, shade them flatly."""
    d = np.asarray(down_c, np.float64) / np.linalg.norm(down_c) + rng.normal(0, 0.2, 3)
    lights = [(d, 1.0 - rng.uniform(0, 0.15, 3), rng.uniform(2.0, 4.5))]
    if rng.random() < 0.7:
        lights.append((_from_camera_side(rng, 0.5), 1.0 - rng.uniform(0, 0.25, 3), rng.uniform(0.3, 1.0)))
    ambient = rng.uniform(0.05, 0.25) * (1.0 - rng.uniform(0, 0.15, 3))
    return lights, ambient


def sample_materials(renderer, obj_ids, p_gloss: float, rng: np.random.Generator,
                     roughness=(0.15, 0.55), metallic=(0.0, 0.2)) -> None:
    """Each object, with probability ``p_gloss``, glossy (low roughness) and partly metallic
    for the next renders; the others get the matte default back."""
    for oid in obj_ids:
        glossy = rng.random() < p_gloss
        r, m = rng.uniform(*roughness), rng.uniform(*metallic)  # drawn either way: one draw count per object
        if glossy:
            renderer.set_material(oid, metallic=m, roughness=r)
        else:
            renderer.set_material(oid)


# --------------------------------------------------------------------------- camera effects


def jitter_colours(rgb: np.ndarray, mask: np.ndarray, box, rng: np.random.Generator,
                   strength: float = 0.15) -> None:
    """Material / vertex-colour jitter of one object in image space: per-channel gain and
    a saturation change inside ``mask`` (in place); ``strength`` 0: none (the same draws).
    ``box``: the mask's (x, y, w, h) as ``visibility.mask_box`` gives it (w <= 0 when empty);
    only that part of the frame is touched."""
    x, y, w, h = (int(v) for v in box)
    if w <= 0 or h <= 0:
        return
    gain, saturation = rng.uniform(1 - strength, 1 + strength, 3), rng.uniform(0.8, 1.5)
    if strength <= 0:  # the objects' own colours; drawn all the same, so the scenes that follow stay
        return
    sub, m = rgb[y:y + h, x:x + w], mask[y:y + h, x:x + w]
    px = sub[m].astype(np.float32)
    px *= gain  # in place: float32, as the images of before
    grey = px.mean(axis=1, keepdims=True)
    px = grey + (px - grey) * saturation
    sub[m] = np.clip(px, 0, 255).astype(np.uint8)


def composite(background: np.ndarray, render: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Render over background with a one-pixel feathered edge (stands in for anti-aliasing).
    Only the mask's box (and the blur's reach around it) is blended: elsewhere the result is
    the background."""
    out = background.copy()
    x, y, w, h = mask_box(mask)
    if w <= 0:
        return out
    H, W = mask.shape
    ys, xs = slice(max(0, y - 2), min(H, y + h + 2)), slice(max(0, x - 2), min(W, x + w + 2))
    m = mask[ys, xs]
    a = cv2.GaussianBlur(m.astype(np.float32), (3, 3), 0.6)[..., None]
    a = np.maximum(a, m[..., None])  # keep the object's own pixels opaque
    out[ys, xs] = (render[ys, xs] * a + background[ys, xs] * (1 - a)).astype(np.uint8)
    return out


def camera_effects(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Exposure, contrast, saturation and white balance, blur (defocus or motion), sensor noise."""
    c, b = rng.uniform(0.7, 1.2), rng.uniform(-30, 30)                     # contrast, brightness
    sat_gain = rng.uniform(0.8, 1.4)                                        # saturation
    wb = rng.uniform(0.88, 1.12, 3)                                         # white balance
    # the four are one affine colour map, applied in one pass:
    # wb * (grey + sat_gain (f - grey)) with f = c (img - 128) + 128 + b, grey the channel mean
    sat = sat_gain * np.eye(3) + (1 - sat_gain) / 3.0
    A = np.diag(wb) @ sat * c
    offset = np.diag(wb) @ sat @ np.full(3, 128 * (1 - c) + b)
    f = cv2.transform(img.astype(np.float32), np.hstack([A, offset[:, None]]).astype(np.float32))
    r = rng.random()
    if r < 0.3:
        s = rng.uniform(0.3, 1.2)
        f = cv2.GaussianBlur(f, (0, 0), s)
    elif r < 0.6:  # the camera's own sharpening (real LM-O crops have 2-8x the Laplacian energy)
        f = cv2.addWeighted(f, 1.8, cv2.GaussianBlur(f, (0, 0), 1.0), -0.8, 0)
    elif r < 0.7:
        k = int(rng.integers(3, 8))
        kernel = np.zeros((k, k), np.float32)
        kernel[k // 2] = 1.0 / k
        M = cv2.getRotationMatrix2D(((k - 1) / 2, (k - 1) / 2), rng.uniform(0, 180), 1.0)
        kernel = cv2.warpAffine(kernel, M, (k, k))
        f = cv2.filter2D(f, -1, kernel / max(kernel.sum(), 1e-6))
    # sensor noise: OpenCV's generator, seeded from ``rng`` (numpy's normal draws took 11 ms
    # of a 640x480 frame's ~150 here, OpenCV's 3.6)
    sigma = float(rng.uniform(2, 9))
    cv2.setRNGSeed(int(rng.integers(2 ** 31)))
    noise = np.empty_like(f)
    cv2.randn(noise, (0.0,) * f.shape[2], (sigma,) * f.shape[2])
    f += noise
    return np.clip(f, 0, 255).astype(np.uint8)
