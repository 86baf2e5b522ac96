import filecmp
import shutil
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from tracker.core.bop import load_scene
from tracker.core.errors import UserError
from tracker.core.geometry import project
from tracker.training.synth.engine import SynthConfig, generate

OBJS = [1, 5, 9]  # small models keep the test quick


def _cfg(data_dir, **kw):
    return SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                       obj_ids=list(OBJS), **kw)


@pytest.fixture(scope="module")
def small_split(tmp_path_factory, data_dir):
    out = tmp_path_factory.mktemp("synth")
    rep = generate(_cfg(data_dir, seed=5), out, 8, workers=1, progress=False)
    assert rep.images == 8 and not rep.interrupted
    return out


def raster_silhouette(vertices, faces, K, R, t, size=(640, 480), margin=320, ss=4):
    """Independent of OpenGL: fill every projected triangle at ``ss`` x supersampling (on a
    canvas with a margin, so the part outside the image counts too). Returns the pixel
    coverage (0..1) at image resolution and the margin."""
    uv = (project(vertices, K, R, t) + margin + 0.5) * ss - 0.5
    canvas = np.zeros(((size[1] + 2 * margin) * ss, (size[0] + 2 * margin) * ss), np.uint8)
    tri = np.round(uv[faces] * 4).astype(np.int32)  # 2 bits of sub-pixel precision
    for tr in tri:  # one at a time: fillPoly of many polygons cancels where they overlap
        cv2.fillConvexPoly(canvas, tr, 1, lineType=cv2.LINE_8, shift=2)
    cov = canvas.reshape(size[1] + 2 * margin, ss, size[0] + 2 * margin, ss).mean(axis=(1, 3))
    return cov, margin


def test_annotations_agree_with_an_independent_projection(small_split, lmo_models):
    scene = load_scene(small_split / "000000", require_gt=True)
    assert len(scene.im_ids) == 8
    checked = 0
    for im_id in scene.im_ids:
        K = scene.K(im_id)
        img = scene.read_rgb(im_id)
        assert img.shape == (480, 640, 3)
        for k, g in enumerate(scene.gt[im_id]):
            info = g.info
            m = lmo_models[g.obj_id]
            sil, mg = raster_silhouette(m.vertices, np.asarray(m.mesh.faces), K, g.R, g.t)
            n_all = float(sil.sum())
            inside = sil[mg:mg + 480, mg:mg + 640] > 0
            mask = cv2.imread(str(small_split / "000000" / "mask_visib" / f"{im_id:06d}_{k:06d}.png"), 0) > 0
            assert int(mask.sum()) == info["px_count_visib"]
            assert info["px_count_all"] == pytest.approx(n_all, rel=0.03, abs=30)
            assert 0.0 <= info["visib_fract"] <= 1.0
            if info["px_count_visib"] > 50:
                # visible pixels lie on the object's own silhouette
                assert (mask & inside).sum() >= 0.95 * mask.sum()
                ys, xs = np.nonzero(sil >= 0.5)
                box = [xs.min() - mg, ys.min() - mg, xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]
                assert np.allclose(info["bbox_obj"], box, atol=3)
                checked += 1
    assert checked >= 10


def test_synth_decimates_by_default_and_renders_the_full_meshes_on_request(tmp_path, data_dir):
    """The CLI's default renders meshes decimated to 4,000 faces (recorded in the split);
    --mesh-faces 0 renders the full meshes, which differ from the decimated ones' pixels."""
    from tracker.cli.main import main
    models = str(data_dir / "lmo" / "models")
    for name, extra in (("dec", []), ("full", ["--mesh-faces", "0"])):
        assert main(["synth", "--models", models, "--out", str(tmp_path / name), "--images", "1", "--obj-ids", "8",
                     "--seed", "3", "--workers", "1", *extra]) == 0
    cfg = {n: json.loads((tmp_path / n / "synth_config.json").read_text())["config"] for n in ("dec", "full")}
    assert cfg["dec"]["mesh_faces"] == 4000 and cfg["full"]["mesh_faces"] is None
    a, b = (cv2.imread(str(tmp_path / n / "000000" / "clean" / "000000_000000.png")) for n in ("dec", "full"))
    assert (a > 0).any() and not np.array_equal(a, b)


def test_decimated_meshes_keep_the_annotations_within_tolerance(tmp_path, data_dir, lmo_models):
    """--mesh-faces renders decimated meshes: silhouettes stay close to the full mesh's."""
    rep = generate(_cfg(data_dir, seed=6, mesh_faces=1500), tmp_path, 3, workers=1, progress=False)
    assert rep.images == 3
    scene = load_scene(tmp_path / "000000", require_gt=True)
    for im_id in scene.im_ids:
        for g in scene.gt[im_id]:
            m = lmo_models[g.obj_id]
            sil, mg = raster_silhouette(m.vertices, np.asarray(m.mesh.faces), scene.K(im_id), g.R, g.t)
            assert g.info["px_count_all"] == pytest.approx(float(sil.sum()), rel=0.05, abs=40)


def test_clean_targets_show_the_whole_object_on_black(small_split):
    root = small_split / "000000"
    windows = json.loads((root / "clean_crops.json").read_text())
    scene = load_scene(root, require_gt=True)
    for im_id in scene.im_ids[:3]:
        assert len(windows[str(im_id)]) == len(scene.gt[im_id])
        for k in range(len(scene.gt[im_id])):
            clean = cv2.imread(str(root / "clean" / f"{im_id:06d}_{k:06d}.png"))
            assert clean.shape == (128, 128, 3)
            fg = clean.max(axis=2) > 0
            assert fg.sum() > 500
            # the whole object: nothing touches the border of the window
            assert not (fg[0].any() or fg[-1].any() or fg[:, 0].any() or fg[:, -1].any())


def test_same_seed_same_output(small_split, tmp_path, data_dir):
    again = tmp_path / "again"
    generate(_cfg(data_dir, seed=5), again, 8, workers=2, progress=False)
    a, b = small_split / "000000", again / "000000"
    for name in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json", "clean_crops.json"):
        assert (a / name).read_text() == (b / name).read_text(), name
    for sub in ("rgb", "mask_visib", "clean"):
        files = sorted(p.name for p in (a / sub).iterdir())
        match, mismatch, errors = filecmp.cmpfiles(a / sub, b / sub, files, shallow=False)
        assert not mismatch and not errors, (sub, mismatch[:3])


def test_forked_workers_render_the_same_split(small_split, tmp_path, data_dir):
    """Workers forked from a process without a GL context (the CLI's case) start with its
    meshes and modules, and render the images one in-process worker rendered (small_split)."""
    import subprocess
    import sys
    script = (
        "import sys\n"
        "from tracker.training.synth.engine import SynthConfig, generate, start_method\n"
        f"cfg = SynthConfig(models_dir={str(data_dir / 'lmo' / 'models')!r}, "
        f"backgrounds_dir={str(data_dir / 'backgrounds')!r}, obj_ids={OBJS!r}, seed=5)\n"
        "assert start_method() == 'fork', start_method()\n"
        f"generate(cfg, {str(tmp_path / 'forked')!r}, 8, workers=2, progress=False)\n"
        "from tracker.runtime.render import contexts_made\n"
        "assert contexts_made() == 0  # the parent never made a GL context\n")
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                         cwd=Path(__file__).resolve().parents[1])
    assert res.returncode == 0, res.stderr[-2000:]
    a, b = small_split / "000000", tmp_path / "forked" / "000000"
    for name in ("scene_gt.json", "scene_gt_info.json", "clean_crops.json"):
        assert (a / name).read_text() == (b / name).read_text(), name
    for sub in ("rgb", "mask_visib", "clean"):
        files = sorted(p.name for p in (a / sub).iterdir())
        match, mismatch, errors = filecmp.cmpfiles(a / sub, b / sub, files, shallow=False)
        assert not mismatch and not errors, (sub, mismatch[:3])


def test_no_fork_after_a_gl_context(small_split):
    """This process rendered small_split in-process (a GL context): its pools must spawn."""
    from tracker.training.synth.engine import start_method
    from tracker.runtime.render import contexts_made
    assert contexts_made() > 0 and start_method() == "spawn"


def test_preview_montage(small_split, tmp_path):
    from tracker.training.synth.preview import preview
    p = preview(small_split, tmp_path / "preview.png", n_scenes=4, n_crops=8)
    img = cv2.imread(str(p))
    assert img is not None and img.shape[1] == 1280


def test_bad_input(data_dir, tmp_path):
    with pytest.raises(UserError, match="positive"):
        generate(_cfg(data_dir), tmp_path / "a", 0, workers=1, progress=False)
    with pytest.raises(UserError, match="p-table"):
        generate(_cfg(data_dir, p_table=1.5), tmp_path / "a", 2, workers=1, progress=False)
    with pytest.raises(UserError, match="--gloss"):
        generate(_cfg(data_dir, p_gloss=-0.1), tmp_path / "a", 2, workers=1, progress=False)
    with pytest.raises(UserError, match="distractor style"):
        generate(_cfg(data_dir, distractors="many"), tmp_path / "a", 2, workers=1, progress=False)
    with pytest.raises(UserError, match="lighting 'sun'"):
        generate(_cfg(data_dir, lighting="sun"), tmp_path / "a", 2, workers=1, progress=False)
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "synth_config.json").write_text("{}")
    with pytest.raises(UserError, match="not an empty folder"):
        generate(_cfg(data_dir), tmp_path / "used", 2, workers=1, progress=False)
    cfg = _cfg(data_dir)
    cfg.backgrounds_dir = str(tmp_path / "missing")
    with pytest.raises(UserError, match="backgrounds folder not found"):
        generate(cfg, tmp_path / "b", 2, workers=1, progress=False)
    (tmp_path / "empty").mkdir()
    cfg.backgrounds_dir = str(tmp_path / "empty")
    with pytest.raises(UserError, match="no readable .jpg/.png"):
        generate(cfg, tmp_path / "c", 2, workers=1, progress=False)
    (tmp_path / "empty" / "notes.jpg").write_text("not a photo")  # skipped by its signature
    with pytest.raises(UserError, match="no readable .jpg/.png"):
        generate(cfg, tmp_path / "c2", 2, workers=1, progress=False)
    assert not (tmp_path / "c2" / "000000").exists()
    from tracker.training.synth.randomise import list_backgrounds
    photo = sorted((data_dir / "backgrounds").glob("*.jpg"))[0]
    shutil.copy(photo, tmp_path / "empty" / photo.name)
    assert [p.name for p in list_backgrounds(tmp_path / "empty")] == [photo.name]
    models = tmp_path / "models"
    models.mkdir()
    (models / "obj_000001.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\ngarbage")
    bad = SynthConfig(models_dir=str(models), backgrounds_dir=str(data_dir / "backgrounds"))
    with pytest.raises(UserError, match="unreadable mesh"):
        generate(bad, tmp_path / "d", 2, workers=1, progress=False)


def test_what_workers_load_at_their_start_is_one_error(data_dir, tmp_path, capfd):
    """A photo cut short (decoded by each worker as it starts, for photo distractors) or an
    occluder that is not a mesh (read in the parent first): one error, where an error in a
    worker's start broke the pool with a traceback from each worker and "the renderer died"."""
    bgs = tmp_path / "bgs"
    bgs.mkdir()
    photo = sorted((data_dir / "backgrounds").glob("*.jpg"))[0]
    shutil.copy(photo, bgs / photo.name)
    (bgs / "cut.jpg").write_bytes(photo.read_bytes()[:300])
    cfg = _cfg(data_dir, distractors="hard")
    cfg.backgrounds_dir = str(bgs)
    with pytest.raises(UserError, match="unreadable background image: .*cut.jpg"):
        generate(cfg, tmp_path / "a", 2, workers=2, progress=False)
    assert "Traceback" not in capfd.readouterr().err
    occ = tmp_path / "occ"
    occ.mkdir()
    (occ / "broken.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\ngarbage")
    with pytest.raises(UserError, match="broken.ply: unreadable mesh"):
        generate(_cfg(data_dir, occluders_dir=str(occ)), tmp_path / "b", 2, workers=2, progress=False)
    assert not (tmp_path / "b" / "000000").exists()  # refused before any folder was made


def test_a_photo_smaller_than_a_patch_textures_distractors_too():
    from tracker.training.synth.randomise import distractor_meshes, texture_from_photos
    rng = np.random.default_rng(0)
    meshes = distractor_meshes(rng, 3)
    texture_from_photos(meshes, [np.full((20, 30, 3), 90, np.uint8)], rng)
    assert all(m.visual.vertex_colors.shape == (len(m.vertices), 4) for m in meshes)


def test_sphere_prior_runs(data_dir, tmp_path):
    rep = generate(_cfg(data_dir, seed=1, prior="sphere"), tmp_path, 2, workers=1, progress=False)
    assert rep.images == 2
    scene = load_scene(tmp_path / "000000", require_gt=True)
    assert all(len(v) >= 1 for v in scene.gt.values())


def _table_camera(elevation_deg, dist=900.0):
    from tracker.core.priors import look_at
    el = np.radians(elevation_deg)
    eye = dist * np.array([np.cos(el), 0.0, np.sin(el)])
    R = look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    return R, -R @ eye


def test_table_surface_lies_on_the_plane_the_objects_stand_on():
    import copy
    from tracker.core.camera import LMO_K
    from tracker.training.synth.randomise import table_surface
    h, w = 480, 640
    ramp = np.broadcast_to(np.linspace(0, 255, w, dtype=np.float32)[None, :, None], (h, w, 3)).astype(np.uint8)
    R, t = _table_camera(30.0)
    rng = np.random.default_rng(0)
    draws = copy.deepcopy(rng)
    half, mm_per_px, a = draws.uniform(500, 1500, 2), draws.uniform(400, 1500) / w, draws.uniform(0, 2 * np.pi)
    g = draws.uniform(-0.25, 0.25), draws.uniform(-0.25, 0.25)
    img, mask = table_surface(ramp, LMO_K, R, t, rng)
    assert img.shape == ramp.shape and mask.dtype == bool
    assert mask[-1].all() and not mask[0].any()  # the table below, beyond its edge / the horizon above
    eye = -R.T @ t
    for X, Y in ((30.0, -20.0), (-60.0, 45.0), (0.9 * half[0], 0.0), (1.1 * half[0], 0.0), (0.0, 1.1 * half[1])):
        u, v = project(np.array([[X, Y, 0.0]]), LMO_K, R, t)[0].round().astype(int)
        inside = abs(X) < half[0] and abs(Y) < half[1]
        if not (0 <= u < w and 0 <= v < h):
            continue
        assert mask[v, u] == inside, (X, Y)
        if not inside:
            continue
        # the texture at the table point seen through that pixel's centre, shaded
        ray = R.T @ np.linalg.solve(LMO_K, [u, v, 1.0])
        P = eye - eye[2] / ray[2] * ray
        tx = (np.cos(a) * P[0] - np.sin(a) * P[1]) / mm_per_px + w / 2
        if 0 <= tx <= w - 1:
            shade = 1 + g[0] * (u - w / 2) / w + g[1] * (v - h / 2) / h
            assert abs(int(img[v, u, 0]) - tx * 255 / (w - 1) * shade) <= 2, (X, Y)
    top_down, _ = _table_camera(89.0, 600.0)
    assert table_surface(ramp, LMO_K, top_down, _table_camera(89.0, 600.0)[1], rng)[1].all()


def test_shadows_darken_the_table_near_the_object_only():
    from tracker.core.camera import LMO_K
    from tracker.training.synth.randomise import cast_shadows
    R, t = _table_camera(45.0)
    box = np.array([[x, y, z] for x in (-40, 40) for y in (-40, 40) for z in (0, 120)], float)  # on the table
    img = np.full((480, 640, 3), 200, np.uint8)
    out = cast_shadows(img, [box], np.array([0.3, 0.2, -1.0]), LMO_K, R, t, np.random.default_rng(1))
    assert (out <= img).all() and (out < 150).any()
    foot = project(np.array([[0.0, 0.0, 0.0]]), LMO_K, R, t)[0].round().astype(int)
    assert out[foot[1], foot[0]].max() < 180  # dark at the object's foot
    assert (out[:40] == 200).all()  # untouched far away


def test_the_table_changes_the_pixels_not_the_annotations(data_dir, tmp_path):
    for p in (0.0, 1.0):
        generate(_cfg(data_dir, seed=5, p_table=p), tmp_path / str(p), 2, workers=1, progress=False)
    a, b = tmp_path / "0.0" / "000000", tmp_path / "1.0" / "000000"
    for name in ("scene_gt.json", "scene_gt_info.json", "clean_crops.json"):
        assert filecmp.cmp(a / name, b / name, shallow=False), name
    ia, ib = (cv2.imread(str(d / "rgb" / "000000.jpg")).astype(int) for d in (a, b))
    assert np.abs(ia - ib).mean() > 10  # the table's surface replaced the photo


def test_join_splits_links_the_scenes_in_order(small_split, tmp_path, data_dir):
    from tracker.training.crops import build_training_crops
    from tracker.training.synth.join import join_splits
    other = tmp_path / "other"
    generate(_cfg(data_dir, seed=6, p_table=0.0), other, 2, workers=1, progress=False)
    meta = join_splits(tmp_path / "joined", [small_split, other])
    assert meta["images_written"] == 10 and len(meta["joined"]) == 2
    a, b, j = (build_training_crops(d, 32, jitter=False, progress=False) for d in (small_split, other, tmp_path / "joined"))
    assert np.array_equal(j.obj_id, np.concatenate([a.obj_id, b.obj_id]))
    assert np.array_equal(j.x, np.concatenate([a.x, b.x]))
    with pytest.raises(UserError, match="not empty"):
        join_splits(tmp_path / "joined", [small_split, other])
    with pytest.raises(UserError, match="no synth_config"):
        join_splits(tmp_path / "j2", [small_split, tmp_path])
    third = tmp_path / "third"
    generate(SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                         obj_ids=[1, 5]), third, 1, workers=1, progress=False)
    with pytest.raises(UserError, match="differ in obj_ids"):
        join_splits(tmp_path / "j3", [small_split, third])
    import shutil
    broken = tmp_path / "broken"
    shutil.copytree(other, broken)
    (broken / "000000" / "scene_gt.json").write_text("{not json")
    with pytest.raises(UserError, match="scene_gt.json"):
        join_splits(tmp_path / "j4", [small_split, broken])
    assert not any((tmp_path / j).exists() for j in ("j2", "j3", "j4"))


def test_gloss_changes_the_object_pixels_not_the_annotations(data_dir, tmp_path):
    for p in (0.0, 1.0):
        generate(_cfg(data_dir, seed=5, p_table=0.0, p_gloss=p), tmp_path / str(p), 2, workers=1, progress=False)
    a, b = tmp_path / "0.0" / "000000", tmp_path / "1.0" / "000000"
    for name in ("scene_gt.json", "scene_gt_info.json", "clean_crops.json"):
        assert filecmp.cmp(a / name, b / name, shallow=False), name
    for f in sorted((a / "clean").iterdir()):  # the reconstruction targets stay matte
        assert filecmp.cmp(f, b / "clean" / f.name, shallow=False), f.name
    ia, ib = (cv2.imread(str(d / "rgb" / "000000.jpg")).astype(int) for d in (a, b))
    masks = sorted((a / "mask_visib").glob("000000_*.png"))
    on = np.any([cv2.imread(str(m), cv2.IMREAD_GRAYSCALE) > 0 for m in masks], axis=0)
    diff = np.abs(ia - ib).sum(axis=2)
    assert diff[on].mean() > 5 * max(diff[~on].mean(), 0.5)  # the objects changed, the background did not


def test_overhead_lighting_changes_the_object_pixels_not_the_scenes(data_dir, tmp_path):
    for light in ("camera", "overhead"):
        generate(_cfg(data_dir, seed=5, p_table=0.0, lighting=light), tmp_path / light, 2, workers=1, progress=False)
    a, b = tmp_path / "camera" / "000000", tmp_path / "overhead" / "000000"
    for name in ("scene_gt.json", "scene_gt_info.json", "clean_crops.json"):
        assert filecmp.cmp(a / name, b / name, shallow=False), name
    for f in sorted((a / "clean").iterdir()):  # the reconstruction targets keep their neutral light
        assert filecmp.cmp(f, b / "clean" / f.name, shallow=False), f.name
    ia, ib = (cv2.imread(str(d / "rgb" / "000000.jpg")).astype(int) for d in (a, b))
    masks = sorted((a / "mask_visib").glob("000000_*.png"))
    on = np.any([cv2.imread(str(m), cv2.IMREAD_GRAYSCALE) > 0 for m in masks], axis=0)
    diff = np.abs(ia - ib).sum(axis=2)
    assert diff[on].mean() > 5 * max(diff[~on].mean(), 0.5)


def test_camera_effects_off_keeps_the_scenes(data_dir, tmp_path):
    for on in (True, False):
        generate(_cfg(data_dir, seed=5, p_table=0.0, camera_effects=on), tmp_path / str(on), 2, workers=1,
                 progress=False)
    a, b = tmp_path / "True" / "000000", tmp_path / "False" / "000000"
    for name in ("scene_gt.json", "scene_gt_info.json", "clean_crops.json"):
        assert filecmp.cmp(a / name, b / name, shallow=False), name
    ia, ib = (cv2.imread(str(d / "rgb" / "000000.jpg")).astype(int) for d in (a, b))
    assert np.abs(ia - ib).mean() > 3  # the whole frame's colours and sharpness changed


def test_colour_jitter_off_keeps_the_objects_colours_and_the_scenes(data_dir, tmp_path):
    for s in (0.15, 0.0):
        generate(_cfg(data_dir, seed=5, p_table=0.0, colour_jitter=s), tmp_path / str(s), 2, workers=1, progress=False)
    a, b = tmp_path / "0.15" / "000000", tmp_path / "0.0" / "000000"
    for name in ("scene_gt.json", "scene_gt_info.json", "clean_crops.json"):  # the same draws: the same scenes
        assert filecmp.cmp(a / name, b / name, shallow=False), name
    ia, ib = (cv2.imread(str(d / "rgb" / "000000.jpg")).astype(int) for d in (a, b))
    masks = sorted((a / "mask_visib").glob("000000_*.png"))
    on = np.any([cv2.imread(str(m), cv2.IMREAD_GRAYSCALE) > 0 for m in masks], axis=0)
    diff = np.abs(ia - ib).sum(axis=2)
    assert diff[on].mean() > 5 * max(diff[~on].mean(), 0.5)  # only the objects changed
    with pytest.raises(UserError, match="--colour-jitter"):
        generate(_cfg(data_dir, colour_jitter=-0.1), tmp_path / "bad", 1, workers=1, progress=False)


def test_overhead_key_light_shines_down_and_dominates():
    from tracker.training.synth.randomise import sample_overhead_lights
    down = np.array([0.0, 0.6, 0.8])  # a camera looking down at the table at about 53 degrees
    rng = np.random.default_rng(0)
    off = []
    for _ in range(500):
        lights, ambient = sample_overhead_lights(rng, down)
        d, _, key = lights[0]
        off.append(np.degrees(np.arccos(d @ down / np.linalg.norm(d))))
        assert all(key > power for _, _, power in lights[1:])
        assert np.all(ambient <= 0.25) and key >= 2.0
    assert 10 < np.median(off) < 20 and max(off) < 90  # around straight down, never from below


def test_an_interrupted_split_keeps_only_annotated_images(data_dir, tmp_path, monkeypatch):
    from tracker.training.synth import engine
    real, calls = engine._render_batch, []

    def stop_in_the_second_batch(args):
        calls.append(1)
        recs = real(args)  # its images are written ...
        if len(calls) == 2:
            raise KeyboardInterrupt  # ... but their records never arrive
        return recs
    monkeypatch.setattr(engine, "_render_batch", stop_in_the_second_batch)
    rep = generate(_cfg(data_dir, seed=5), tmp_path / "s", 1001, workers=1, batch=2, progress=False)
    assert rep.interrupted and rep.images == 2
    assert not (tmp_path / "s" / "000001").exists()  # the second chunk never got an image
    scene = load_scene(tmp_path / "s" / "000000", require_gt=True)
    assert scene.im_ids == [0, 1]
    for sub in ("rgb", "mask_visib", "clean"):
        assert {int(f.name[:6]) for f in (tmp_path / "s" / "000000" / sub).iterdir()} == {0, 1}, sub


def test_household_shapes_stand_upright_with_their_features():
    from tracker.training.synth.randomise import household_meshes
    mug, cup, bottle = household_meshes(np.random.default_rng(0), 3)
    (x0, y0, _), (x1, y1, _) = mug.bounds
    assert x1 - x0 > 1.3 * (y1 - y0)  # the handle sticks out on one side only
    assert x1 > -x0 + 20
    v = np.asarray(cup.vertices)
    z0, z1 = v[:, 2].min(), v[:, 2].max()
    width = lambda m: np.abs(v[m, :2]).max()
    assert width(v[:, 2] > z1 - 1) > 1.15 * width(v[:, 2] < z0 + 1)  # wider at the rim
    v = np.asarray(bottle.vertices)
    assert np.ptp(v[:, 2]) > 1.5 * np.ptp(v[:, 0])  # tall
    top = v[:, 2] > v[:, 2].max() - 1
    assert np.abs(v[top, :2]).max() < 0.5 * np.abs(v[:, :2]).max()  # a neck


@pytest.mark.parametrize("style", ["hard", "household"])
def test_photo_distractors_are_textured_tinted_and_unannotated(data_dir, tmp_path, style):
    from dataclasses import asdict

    from tracker.training.synth import engine
    from tracker.training.synth.randomise import target_palette
    cfg = _cfg(data_dir, seed=3, distractors=style)
    engine._init_worker(asdict(cfg))
    try:
        assert engine._W["n_dis"] == 36
        cols = [np.unique(np.asarray(engine._W["scene"]._meshes[engine.DISTRACTOR_BASE + i].primitives[0].color_0)[:, :3],
                          axis=0).shape[0] for i in (0, 1, 2, 33, 34, 35)]
        assert min(cols) > 20  # a photo's patch, not a flat colour
        if style == "household":  # the second half: mugs, cups and bottles
            from tracker.training.synth.randomise import household_meshes
            mug = household_meshes(np.random.default_rng([3, 10]), 1)[0]
            assert np.allclose(engine._W["verts"][engine.DISTRACTOR_BASE + 18], mug.vertices)
        for k in range(20):
            inst, n_t, _, _ = engine._sample_instances(np.random.default_rng([3, k]), cfg)
            n_d = sum(i >= engine.DISTRACTOR_BASE for i, _, _ in inst)
            assert n_d >= engine.HARD_DISTRACTORS_PER_IMAGE[0] and all(i in OBJS for i, _, _ in inst[:n_t])
    finally:
        for k in ("scene", "crop"):
            engine._W.pop(k).close()
    # the palette is the targets' own colours
    from tracker.core.meshes import load_models
    models = load_models(cfg.models_dir, OBJS)
    pal = target_palette([models[o].mesh for o in OBJS], np.random.default_rng(0), per_mesh=4)
    own = np.concatenate([np.asarray(models[o].mesh.visual.vertex_colors)[:, :3] for o in OBJS]) / 255.0
    assert pal.shape == (12, 3) and all(np.abs(own - c).sum(1).min() < 1e-9 for c in pal)
    # a split renders and only the targets are annotated
    generate(cfg, tmp_path / "h", 2, workers=1, progress=False)
    scene = load_scene(tmp_path / "h" / "000000", require_gt=True)
    assert scene.im_ids == [0, 1] and {g.obj_id for i in scene.im_ids for g in scene.gt[i]} <= set(OBJS)


def test_a_render_worker_that_dies_is_replaced_and_its_images_rendered_again(data_dir, tmp_path, monkeypatch):
    """A worker that dies mid-split (as a Mesa segfault does) no longer hangs the job: the pool
    notices, a fresh one renders the lost batch again, and the split is whole and consistent."""
    from tracker.training.synth import engine
    marker = tmp_path / "crashed"
    monkeypatch.setenv(engine.CRASH_HOOK, f"5:{marker}")
    rep = generate(_cfg(data_dir, seed=5), tmp_path / "s", 8, workers=2, batch=2, progress=False)
    assert marker.exists()  # a worker did die, at image 5
    assert rep.images == 8 and not rep.interrupted
    scene = load_scene(tmp_path / "s" / "000000", require_gt=True)
    assert scene.im_ids == list(range(8))
    assert {int(f.name[:6]) for f in (tmp_path / "s" / "000000" / "rgb").iterdir()} == set(range(8))
    # the re-rendered image is the one its seed draws: the same as in a split made without a crash
    monkeypatch.delenv(engine.CRASH_HOOK)
    generate(_cfg(data_dir, seed=5), tmp_path / "t", 8, workers=1, batch=2, progress=False)
    a, b = (load_scene(tmp_path / d / "000000", require_gt=True) for d in ("s", "t"))
    assert a.gt[5][0].obj_id == b.gt[5][0].obj_id and np.allclose(a.gt[5][0].t, b.gt[5][0].t)


def test_a_batch_that_always_kills_its_worker_ends_the_job_with_an_error(data_dir, tmp_path, monkeypatch):
    from tracker.training.synth import engine
    monkeypatch.setenv(engine.CRASH_HOOK, "3:")  # image 3 kills every worker that renders it
    # which other batches finish before each pool breaks is a race; the failing one is always left
    with pytest.raises(UserError, match=r"renderer died 3 times in a row .*images [0-3]-[3-5] left"):
        generate(_cfg(data_dir, seed=5), tmp_path / "s", 6, workers=2, batch=2, progress=False)
    meta = json.loads((tmp_path / "s" / "synth_config.json").read_text())
    assert meta["failed"] and meta["images_written"] < 6
    kept = load_scene(tmp_path / "s" / "000000").im_ids if meta["images_written"] else []
    assert 3 not in kept and len(kept) == meta["images_written"]  # what is there is whole and annotated
    rgb = tmp_path / "s" / "000000" / "rgb"
    assert {int(f.name[:6]) for f in rgb.iterdir()} == set(kept) if rgb.is_dir() else not kept


def test_shards_joined_are_the_split_rendered_at_once(small_split, tmp_path, data_dir):
    """synth --shard K/N: disjoint, deterministic parts; joined, the same images and annotations."""
    from tracker.training.synth.engine import shard_range
    from tracker.training.synth.join import join_splits
    assert [list(shard_range(8, (k, 3))) for k in range(3)] == [[0, 1], [2, 3, 4], [5, 6, 7]]
    with pytest.raises(UserError, match="0 <= K < N"):
        shard_range(8, (3, 3))
    parts = []
    for k in (0, 1, 2):
        parts.append(tmp_path / f"part{k}")
        generate(_cfg(data_dir, seed=5), parts[-1], 8, workers=1, progress=False, shard=(k, 3))
    assert json.loads((parts[1] / "synth_config.json").read_text())["shard"] == [1, 3]
    join_splits(tmp_path / "joined", parts)
    whole = load_scene(small_split / "000000", require_gt=True)
    got = {}
    for d in sorted((tmp_path / "joined").iterdir()):
        if d.is_dir():
            sc = load_scene(d, require_gt=True)
            for i in sc.im_ids:
                got[i] = (sc, d)
    assert sorted(got) == list(range(8))
    for i, (sc, _) in got.items():
        assert np.array_equal(sc.read_rgb(i), whole.read_rgb(i)), i
        assert [g.obj_id for g in sc.gt[i]] == [g.obj_id for g in whole.gt[i]]
        assert np.allclose([g.t for g in sc.gt[i]], [g.t for g in whole.gt[i]])
    with pytest.raises(UserError, match="share images 2-4"):
        join_splits(tmp_path / "twice", [parts[1], parts[1]])
    with pytest.raises(UserError, match="same settings and seed"):
        join_splits(tmp_path / "overlap", [small_split, parts[2]])


def test_a_time_limited_split_stops_with_a_consistent_split_of_what_was_done(data_dir, tmp_path):
    """``seconds`` (build's budget): once the time is up and ``min_images`` are done, rendering
    stops, and the split holds exactly the images whose records arrived."""
    import json
    out = tmp_path / "t"
    rep = generate(_cfg(data_dir, seed=5), out, 20, workers=1, batch=1, progress=False, seconds=0.0, min_images=3)
    assert rep.time_limited and not rep.interrupted and rep.images == 3
    scene = load_scene(out / "000000", require_gt=True)
    assert scene.im_ids == [0, 1, 2]
    for sub in ("rgb", "mask_visib", "clean"):
        assert {int(f.name[:6]) for f in (out / "000000" / sub).iterdir()} == {0, 1, 2}, sub
    meta = json.loads((out / "synth_config.json").read_text())
    assert meta["time_limited"] and meta["images_written"] == 3 and not meta.get("failed")


def test_repeat_objects_fills_an_image_of_few_objects_with_instances_of_them(data_dir, tmp_path):
    """``repeat_objects``: a split of two objects draws 3-8 instances per image (each object at
    least once), annotated one by one as BOP allows; without it, each object once."""
    from dataclasses import asdict

    from tracker.training.synth import engine
    two = [1, 9]
    cfg = SynthConfig(models_dir=str(data_dir / "lmo" / "models"), backgrounds_dir=str(data_dir / "backgrounds"),
                      obj_ids=two, seed=6, repeat_objects=True)
    engine._init_worker(asdict(cfg))
    try:
        counts = []
        for k in range(20):
            inst, n_t, _, _ = engine._sample_instances(np.random.default_rng([6, k]), cfg)
            targets = [i for i, _, _ in inst[:n_t]]
            assert set(targets) == set(two) and 3 <= n_t <= 8
            counts.append(n_t)
            once, n_once, _, _ = engine._sample_instances(np.random.default_rng([6, k]), SynthConfig(
                **{**asdict(cfg), "repeat_objects": False}))
            assert sorted(i for i, _, _ in once[:n_once]) == two
        assert max(counts) > 3
    finally:
        for k in ("scene", "crop"):
            engine._W.pop(k).close()
    generate(cfg, tmp_path / "r", 2, workers=1, progress=False)
    scene = load_scene(tmp_path / "r" / "000000", require_gt=True)
    for i in scene.im_ids:
        ids = [g.obj_id for g in scene.gt[i]]
        assert len(ids) >= 3 and set(ids) == set(two)
        for k in range(len(scene.gt[i])):  # every instance has its own mask and clean target
            assert (tmp_path / "r" / "000000" / "mask_visib" / f"{i:06d}_{k:06d}.png").is_file()
            assert (tmp_path / "r" / "000000" / "clean" / f"{i:06d}_{k:06d}.png").is_file()
    assert json.loads((tmp_path / "r" / "synth_config.json").read_text())["config"]["repeat_objects"] is True


def test_a_split_made_from_relative_folders_finds_its_meshes_from_anywhere(data_dir, tmp_path, monkeypatch):
    """synth_config.json records absolute folders: `train` (or a resumed `build`) run from
    another working folder still finds the meshes and backgrounds."""
    monkeypatch.chdir(data_dir)
    cfg = SynthConfig(models_dir="lmo/models", backgrounds_dir="backgrounds", obj_ids=[1], objects_per_image=(1, 1))
    generate(cfg, tmp_path / "split", 1, workers=1, progress=False)
    monkeypatch.chdir(tmp_path)
    c = json.loads((tmp_path / "split" / "synth_config.json").read_text())["config"]
    assert Path(c["models_dir"]).is_absolute() and (Path(c["models_dir"]) / "obj_000001.ply").is_file()
    assert Path(c["backgrounds_dir"]).is_absolute() and Path(c["backgrounds_dir"]).is_dir()


def test_without_the_decimation_library_synth_says_what_to_do(data_dir, tmp_path, monkeypatch):
    """The default decimated meshes need fast_simplification: without it the job ends with the
    one-line error naming the fix, from the parent before any worker starts (not a broken
    pool retried three times), and renders nothing."""
    import trimesh
    from tracker.training import decimate as dec

    def missing(*a, **k):
        raise ImportError("No module named 'fast_simplification'")
    monkeypatch.setenv("AUTOPOSE_CACHE", str(tmp_path / "cache"))  # nothing cached yet
    monkeypatch.setattr(trimesh.Trimesh, "simplify_quadric_decimation", missing)
    monkeypatch.setattr(dec, "_write", lambda *a: pytest.fail("nothing to cache"))
    with pytest.raises(UserError, match="needs fast_simplification.*--mesh-faces 0"):
        generate(_cfg(data_dir), tmp_path / "out", 4, workers=2, progress=False)
    assert not list((tmp_path / "out").rglob("*.jpg"))
