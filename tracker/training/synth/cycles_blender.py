"""The Blender side of :mod:`tracker.training.synth.cycles`: runs inside Blender's own Python
(``blender --background --factory-startup --python THIS``), never imported by autopose.

It reads one JSON request a line on stdin and answers each with one line on stdout that
starts with ``AUTOPOSE``. Requests:
- ``{"op": "init", "meshes": {id: PLY path (mm, vertex colours)}, "width", "height",
  "samples", "threads", "roughness", "specular"}``: the scene, the camera and one
  material per mesh (the mesh's vertex colours through a Principled BSDF).
- ``{"op": "render", "K": 9 floats, "instances": [[id, R (9, model -> OpenCV camera),
  t (3, mm)]], "lights": [[direction (3, OpenCV camera frame, the way the light travels),
  rgb, intensity]], "ambient": float, "out": PNG path}``: an RGBA image, transparent where no
  object is.

Conventions (checked against pyrender in tests/test_cycles.py): the OpenCV camera is Blender's
camera at the origin, every model matrix premultiplied by diag(1, -1, -1) (Blender's camera
looks along -z with y up); pixel centres at integer coordinates (BOP, OpenCV), hence the
(W - 1) / 2 in the lens shift; the "Standard" view transform (plain sRGB, not Filmic).
"""
import json
import sys
import traceback

import bpy
from mathutils import Matrix, Vector

F = Matrix(((1, 0, 0, 0), (0, -1, 0, 0), (0, 0, -1, 0), (0, 0, 0, 1)))
SCALE = Matrix.Diagonal((0.001, 0.001, 0.001, 1.0))  # mm -> m
STATE = {}


def answer(text: str) -> None:
    sys.stdout.write(f"AUTOPOSE {text}\n")
    sys.stdout.flush()


def init(req: dict) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = int(req["samples"])
    sc.cycles.use_denoising = False
    sc.render.threads_mode = "FIXED"
    sc.render.threads = int(req["threads"])
    sc.render.resolution_x, sc.render.resolution_y = int(req["width"]), int(req["height"])
    sc.render.resolution_percentage = 100
    sc.render.film_transparent = True
    sc.view_settings.view_transform = "Standard"
    sc.render.image_settings.file_format = "PNG"
    sc.render.image_settings.color_mode = "RGBA"
    sc.world = bpy.data.worlds.new("world")
    sc.world.use_nodes = True
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    cam.data.sensor_fit = "HORIZONTAL"
    cam.data.sensor_width = 36.0
    cam.data.clip_start, cam.data.clip_end = 0.01, 100.0
    sc.collection.objects.link(cam)
    sc.camera = cam
    meshes = {}
    for mid, path in req["meshes"].items():
        bpy.ops.import_mesh.ply(filepath=path)
        o = bpy.context.selected_objects[0]
        mat = bpy.data.materials.new(f"material_{mid}")
        mat.use_nodes = True
        nt = mat.node_tree
        bsdf = nt.nodes["Principled BSDF"]
        nt.links.new(nt.nodes.new("ShaderNodeVertexColor").outputs["Color"], bsdf.inputs["Base Color"])
        bsdf.inputs["Roughness"].default_value = float(req["roughness"])
        bsdf.inputs["Specular"].default_value = float(req["specular"])
        o.data.materials.append(mat)
        o.hide_render = True
        meshes[str(mid)] = [o]
    STATE.update(scene=sc, camera=cam, meshes=meshes, suns=[])


def render(req: dict) -> None:
    sc, cam = STATE["scene"], STATE["camera"]
    W, H = sc.render.resolution_x, sc.render.resolution_y
    fx, _, cx, _, fy, cy = req["K"][:6]
    cam.data.lens = fx * cam.data.sensor_width / W
    cam.data.shift_x = ((W - 1) / 2 - cx) / W
    cam.data.shift_y = (cy - (H - 1) / 2) / W
    sc.render.pixel_aspect_x, sc.render.pixel_aspect_y = 1.0, fx / fy
    for pool in STATE["meshes"].values():
        for o in pool:
            o.hide_render = True
    used = {}
    for mid, R, t in req["instances"]:
        pool = STATE["meshes"][str(mid)]
        k = used.get(str(mid), 0)
        used[str(mid)] = k + 1
        if k == len(pool):  # one more instance of this mesh: a linked duplicate
            pool.append(pool[0].copy())
            sc.collection.objects.link(pool[-1])
        o = pool[k]
        o.hide_render = False
        o.matrix_world = F @ Matrix(((R[0], R[1], R[2], t[0] / 1000), (R[3], R[4], R[5], t[1] / 1000),
                                     (R[6], R[7], R[8], t[2] / 1000), (0, 0, 0, 1))) @ SCALE
    suns = STATE["suns"]  # kept from image to image (new ones each time would pile up as orphan data)
    while len(suns) < len(req["lights"]):
        sun = bpy.data.objects.new(f"sun{len(suns)}", bpy.data.lights.new(f"sun{len(suns)}", type="SUN"))
        sun.data.angle = 0.1
        sc.collection.objects.link(sun)
        suns.append(sun)
    for i, sun in enumerate(suns):
        if i >= len(req["lights"]):
            sun.data.energy = 0.0
            continue
        d, rgb, intensity = req["lights"][i]
        sun.data.energy, sun.data.color = float(intensity), rgb
        sun.rotation_euler = (F.to_3x3() @ Vector(d)).to_track_quat("-Z", "Y").to_euler()  # a sun shines along its -z
    sc.world.node_tree.nodes["Background"].inputs[1].default_value = float(req["ambient"])
    sc.render.filepath = req["out"]
    bpy.ops.render.render(write_still=True)


def main() -> None:
    for line in sys.stdin:
        if not line.strip():
            continue
        try:
            req = json.loads(line)
            {"init": init, "render": render}[req["op"]](req)
            answer("ok")
        except Exception as e:  # one line back to the worker, which raises it there
            traceback.print_exc(file=sys.stderr)
            answer("error " + f"{type(e).__name__}: {e}".replace("\n", " "))


main()
