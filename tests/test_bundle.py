"""Bundles whose hashes are right but whose contents are not, and changes that re-hash a bundle."""
import json
import shutil

import pytest

from tests.conftest import REPO
from tracker.bundle import open_bundle, write_manifest
from tracker.errors import UserError
from tracker.estimator import PoseEstimator


@pytest.fixture()
def bundle(tmp_path):
    b = tmp_path / "lmo"
    shutil.copytree(REPO / "models" / "lmo", b)
    return b


def _rehash(b, change=None):
    """Re-hash the folder as the bundle's maker would: the tampering is then invisible to the hashes."""
    m = {k: v for k, v in json.loads((b / "manifest.json").read_text()).items() if k not in ("files", "format")}
    if change:
        change(m)
    write_manifest(b, m)


def test_a_hashed_file_of_the_wrong_kind_is_refused(bundle):
    shutil.copy(bundle / "codebook_aae.joblib", bundle / "pose_head.joblib")
    _rehash(bundle)
    with pytest.raises(UserError, match="Codebook, not a PoseHead"):
        PoseEstimator(bundle)
    (bundle / "pose_head.joblib").write_bytes(b"")
    _rehash(bundle)
    with pytest.raises(UserError, match="unreadable pose_head"):
        PoseEstimator(bundle)


@pytest.mark.parametrize("change, what", [
    (lambda m: m.pop("objects"), "objects"),
    (lambda m: m["objects"][0].pop("diameter"), "diameter"),
    (lambda m: m.update(input_size="abc"), "input_size"),
])
def test_a_malformed_manifest_is_refused(bundle, change, what):
    _rehash(bundle, change)
    with pytest.raises(UserError, match=f"malformed manifest.*{what}"):
        open_bundle(bundle)


def test_decimate_rewrites_the_overlay_meshes_of_a_bundle_that_has_them(bundle):
    from tracker.decimate import add_overlay_meshes
    before = open_bundle(bundle).manifest
    assert before["overlay_faces"] != 400 and all("overlay_mesh" in o for o in before["objects"])
    add_overlay_meshes(bundle, 400, log=lambda *a: None)
    after = open_bundle(bundle).manifest  # verifies every hash again
    assert after["overlay_faces"] == 400
    rel = after["objects"][0]["overlay_mesh"]
    assert after["files"][rel]["sha256"] != before["files"][rel]["sha256"]


def test_a_staged_change_lands_whole_or_not_at_all(bundle):
    from tracker.bundle import staged_bundle, sha256
    before = sha256(bundle / "manifest.json")
    with pytest.raises(KeyboardInterrupt):
        with staged_bundle(bundle, bundle) as stage:
            (stage / "detector.onnx").write_bytes(b"half written")
            raise KeyboardInterrupt  # Ctrl-C before the manifest is re-hashed
    assert sha256(bundle / "manifest.json") == before
    open_bundle(bundle)  # every hash still matches: the old bundle, untouched
    assert sorted(p.name for p in bundle.parent.iterdir()) == ["lmo"]  # no staging folder left

    with staged_bundle(bundle, bundle) as stage:
        m = {k: v for k, v in json.loads((stage / "manifest.json").read_text()).items() if k not in ("files", "format")}
        m["name"] = "changed"
        write_manifest(stage, m)
    assert open_bundle(bundle).manifest["name"] == "changed"
    assert sorted(p.name for p in bundle.parent.iterdir()) == ["lmo"]

