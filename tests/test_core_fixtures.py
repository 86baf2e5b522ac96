"""Core I/O, ground truth and scoring on the project's own small fixtures (tests/fixtures: two
meshes and a two-frame BOP scene, made by tests/fixtures/make_fixtures.py): these run without
the shared data."""
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tracker.core.bop import Estimate, load_models_info, load_scene, write_results
from tracker.core.meshes import compute_models_info, load_models

FIX = Path(__file__).parent / "fixtures"
SCENE = FIX / "scene" / "000001"


def test_the_fixture_scene_reads_as_bop():
    s = load_scene(SCENE, require_gt=True)
    assert sorted(s.gt) == [0, 1] and s.read_rgb(0).shape == (120, 160, 3)
    assert np.allclose(s.K(1), [[150, 0, 80], [0, 150, 60], [0, 0, 1]])
    g = s.gt[0][1]
    assert g.obj_id == 2 and np.allclose(g.R @ g.R.T, np.eye(3), atol=1e-6) and g.t[2] == 280.0
    assert s.gt[1][1].info["visib_fract"] < 0.1  # the cylinder behind the box in frame 1


def test_models_info_of_the_fixture_meshes():
    computed = compute_models_info(load_models(FIX / "models"))
    stored = load_models_info(FIX / "models" / "models_info.json")
    box, cyl = computed[1], computed[2]
    assert box["diameter"] == pytest.approx(np.sqrt(60 ** 2 + 40 ** 2 + 20 ** 2), rel=1e-6)
    assert box["size_x"] == pytest.approx(60) and box["min_z"] == pytest.approx(-10)
    assert len(box["symmetries_discrete"]) == 3  # a box: three 180-degree turns
    # a 32-sided cylinder: found as discrete turns (continuous symmetries are not detected; they
    # come from a models_info file where an object has them)
    assert len(cyl["symmetries_discrete"]) >= 1 and not cyl.get("symmetries_continuous")
    assert stored[1]["diameter"] == pytest.approx(box["diameter"])


def test_rendered_ground_truth_boxes_match_the_scenes_info(tmp_path):
    """Without scene_gt_info.json the visible boxes are rendered from the known objects; on this
    scene, whose only occluders are known, they agree with the stored ones."""
    from tracker.evaluation.ground_truth import gt_boxes
    stored, _ = gt_boxes(load_scene(SCENE, require_gt=True), None, [0, 1])
    bare = tmp_path / "000001"
    shutil.copytree(SCENE, bare)
    (bare / "scene_gt_info.json").unlink()
    rendered, source = gt_boxes(load_scene(bare, require_gt=True), load_models(FIX / "models"), [0, 1])
    assert "render" in source
    for i in (0, 1):
        for (b1, v1), (b2, v2) in zip(stored[i], rendered[i]):
            assert np.abs(np.asarray(b1) - np.asarray(b2)).max() <= 2 and abs(v1 - v2) < 0.1


def test_scoring_the_ground_truth_gives_full_recall_and_a_shift_fails_it(tmp_path):
    from tracker.evaluation.scoring import score_results
    s = load_scene(SCENE, require_gt=True)

    def score(shift_mm):
        ests = [Estimate(1, i, g.obj_id, 1.0, g.R, g.t + [shift_mm, 0, 0], 0.01) for i in s.gt for g in s.gt[i]]
        write_results(tmp_path / f"r{shift_mm}.csv", ests)
        return score_results(tmp_path / f"r{shift_mm}.csv", SCENE, FIX / "models", scene_id=1)
    exact = score(0.0)
    assert exact["n_gt"] == 3  # the 4 % visible cylinder does not count
    assert exact["add_recall"] == exact["ar_mssd"] == exact["ar_mspd"] == 1.0
    off = score(40.0)  # more than 10 % of either diameter
    assert off["add_recall"] == 0.0 and off["ar_mssd"] < 1.0


def test_a_manifest_round_trips_through_its_one_reader_and_writer(tmp_path):
    from tracker.core.bundle import open_bundle, write_manifest
    from tracker.core.manifest import Manifest, ObjectEntry
    b = tmp_path / "b"
    (b / "meshes").mkdir(parents=True)
    shutil.copy(FIX / "models" / "obj_000001.ply", b / "meshes")
    (b / "encoder.onnx").write_bytes(b"not read here")
    m = Manifest(name="b", method="cvam", input_size=64, latent_size=16,
                 objects=[ObjectEntry(1, "meshes/obj_000001.ply", 74.8, "box")], artefacts={"encoder": "encoder.onnx"},
                 extra={"colour_order": "RGB"}, heads={"trees_weight": {"exact": 0.5, "detector": 0.0}})
    write_manifest(b, m)
    back = open_bundle(b).manifest
    assert back.format == 2 and back.objects == m.objects and back.extra == {"colour_order": "RGB"}
    assert set(back.files) == {"encoder.onnx", "meshes/obj_000001.ply"} and back.file_sha256("encoder")
    raw = json.loads((b / "manifest.json").read_text())
    assert raw["colour_order"] == "RGB" and "extra" not in raw
