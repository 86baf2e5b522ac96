import numpy as np

from tracker.core.geometry import box_from_points, iou_matrix, project
from tracker.evaluation.preview import render_gt_overlays
from tracker.runtime.render import Renderer


def test_silhouettes_match_projected_vertices(lmo_dev, lmo_models):
    im_id = lmo_dev.im_ids[0]
    K = lmo_dev.K(im_id)
    gts = lmo_dev.gt[im_id]
    with Renderer(640, 480, {g.obj_id: lmo_models[g.obj_id].mesh for g in gts}) as r:
        for g in gts:
            _, depth = r.render(K, [(g.obj_id, g.R, g.t)], depth_only=True)
            ys, xs = np.nonzero(depth > 0)
            rbox = (xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1)
            pbox = box_from_points(project(lmo_models[g.obj_id].vertices, K, g.R, g.t))
            assert iou_matrix(rbox, pbox)[0, 0] > 0.9
            # rendered depth at the silhouette is about the object's distance
            assert abs(np.median(depth[depth > 0]) - g.t[2]) < 0.6 * np.ptp(lmo_models[g.obj_id].vertices)
        # instances of the same object twice, and a renderer reused across calls
        g = gts[0]
        t2 = g.t + np.array([80.0, 0, 0])
        _, d2 = r.render(K, [(g.obj_id, g.R, g.t), (g.obj_id, g.R, t2)], depth_only=True)
        _, d1 = r.render(K, [(g.obj_id, g.R, g.t)], depth_only=True)
        assert (d2 > 0).sum() > 1.5 * (d1 > 0).sum()
        rgb, d0 = r.render(K, [])
        assert (d0 > 0).sum() == 0 and rgb.max() == 0


def test_gt_overlay_job(lmo_dev, data_dir, tmp_path):
    s = render_gt_overlays(data_dir / "lmo" / "dev", data_dir / "lmo" / "models", tmp_path, max_frames=2,
                           progress=False)
    assert s.frames == 2 and s.instances == sum(len(lmo_dev.gt[i]) for i in lmo_dev.im_ids[:2])
    assert s.box_iou_min > 0.85
    assert (tmp_path / "overlay_montage.png").is_file() and len(list((tmp_path / "overlay").glob("*.png"))) == 2


def test_glossy_material_adds_highlights_and_the_default_comes_back():
    import trimesh
    ball = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    ball.visual.vertex_colors = np.tile([120, 120, 120, 255], (len(ball.vertices), 1))
    K = np.array([[500.0, 0, 64], [0, 500.0, 64], [0, 0, 1]])
    pose = [(1, np.eye(3), np.array([0.0, 0.0, 600.0]))]
    with Renderer(128, 128, {1: ball}) as r:
        matte, depth = r.render(K, pose)
        r.set_material(1, metallic=0.4, roughness=0.15)
        glossy, _ = r.render(K, pose)
        r.set_material(1)
        again, _ = r.render(K, pose)
    on = depth > 0
    # the head light's specular peak: a glossy ball is far brighter at its centre than a matte one
    assert glossy[on].max() > matte[on].max() + 30
    assert np.array_equal(again, matte)


def test_a_colour_factor_tints_an_object_and_the_default_comes_back():
    import trimesh
    box = trimesh.creation.box(extents=(80.0, 80.0, 80.0)).subdivide()
    box.visual.vertex_colors = np.tile([230, 230, 230, 255], (len(box.vertices), 1))
    K = np.array([[500.0, 0, 64], [0, 500.0, 64], [0, 0, 1]])
    pose = [(1, np.eye(3), np.array([0.0, 0.0, 600.0]))]
    with Renderer(128, 128, {1: box}) as r:
        white, depth = r.render(K, pose)
        r.set_material(1, colour=(0.9, 0.8, 0.0))  # linear yellow
        yellow, _ = r.render(K, pose)
        r.set_material(1)
        again, _ = r.render(K, pose)
    on = depth > 0
    w, y = white[on].mean(0), yellow[on].mean(0)
    assert abs(w[0] - w[2]) < 10 and y[0] > y[2] + 100 and y[1] > y[2] + 100
    assert np.array_equal(again, white)


def test_every_one_of_the_max_lights_shines():
    """The shader's light arrays are sized for MAX_LIGHTS directional lights (and one slot for
    the kinds we never use): each of four lights from four sides lights its own side."""
    import trimesh
    from tracker.runtime.render import MAX_LIGHTS
    ball = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    ball.visual.vertex_colors = np.tile([160, 160, 160, 255], (len(ball.vertices), 1))
    K = np.array([[500.0, 0, 64], [0, 500.0, 64], [0, 0, 1]])
    pose = [(1, np.eye(3), np.array([0.0, 0.0, 600.0]))]
    sides = [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)]  # light travels towards -side
    assert MAX_LIGHTS == len(sides)
    spots = [(64 - 35 * x, 64 - 35 * y) for x, y in sides]  # the ball's lit side for each light: (u, v)
    with Renderer(128, 128, {1: ball}, ambient=0.0) as r:
        lights = [((x, y, 0.3), (1.0, 1.0, 1.0), 3.0) for x, y in sides]
        before = None
        for k in range(len(sides)):
            r.set_lights(lights[:k + 1])
            img, _ = r.render(K, pose)
            lit = [int(img[int(v), int(u)].mean()) for u, v in spots]
            if before is not None:  # the k-th light brightens its own side
                assert lit[k] > before[k] + 40, (k, before, lit)
            before = lit
        assert min(before) > 100  # all four on: every side lit
