"""Bundles whose hashes are right but whose contents are not, and changes that re-hash a bundle."""
import json
import shutil

import numpy as np
import pytest

from tests.conftest import REPO
from tracker.core.bundle import open_bundle, sha256
from tracker.core.errors import UserError
from tracker.runtime.estimator import PoseEstimator


@pytest.fixture()
def bundle(tmp_path):
    b = tmp_path / "lmo"
    shutil.copytree(REPO / "models" / "lmo", b)
    return b


def _rehash(b, change=None):
    """Re-hash the folder as the bundle's maker would, with the manifest's JSON edited by ``change``
    (which may break it): the tampering is then invisible to the hashes."""
    m = json.loads((b / "manifest.json").read_text())
    if change:
        change(m)
    m["files"] = {str(p.relative_to(b)): {"sha256": sha256(p), "bytes": p.stat().st_size}
                  for p in sorted(b.rglob("*")) if p.is_file() and p.name != "manifest.json"}
    (b / "manifest.json").write_text(json.dumps(m))


def test_a_hashed_file_of_the_wrong_kind_is_refused(bundle):
    shutil.copy(bundle / "codebook.npz", bundle / "pose_head.npz")
    _rehash(bundle)
    with pytest.raises(UserError, match="unreadable pose head"):
        PoseEstimator(bundle)
    (bundle / "pose_head.json").write_text("")
    _rehash(bundle)
    with pytest.raises(UserError, match="unreadable pose head"):
        PoseEstimator(bundle)


def test_a_pickle_inside_a_bundle_is_never_loaded(bundle, tmp_path):
    """An object array in the .npz (numpy stores it as a pickle) is refused, not unpickled."""
    ran = tmp_path / "ran"

    class Evil:
        def __reduce__(self):
            return (ran.write_text, ("code ran",))
    with np.load(bundle / "pose_head.npz") as z:
        arrays = dict(z)
    key = next(k for k in arrays if k.endswith("rotation.W0"))
    arrays[key] = np.array([Evil()], dtype=object)
    np.savez(bundle / "pose_head.npz", **arrays)
    _rehash(bundle)
    with pytest.raises(UserError, match="unreadable pose head"):
        PoseEstimator(bundle)
    assert not ran.exists()


def test_no_file_in_the_shipped_bundles_is_a_pickle():
    """Loading a bundle must not be able to run code: no pickle anywhere under models/, and
    every array file reads with allow_pickle=False."""
    for p in (REPO / "models").rglob("*"):
        if not p.is_file():
            continue
        head = p.read_bytes()[:2]
        assert not (head[:1] == b"\x80" and head[1:2] in b"\x02\x03\x04\x05"), f"{p} is a pickle"
        assert p.suffix not in (".joblib", ".pkl", ".pickle", ".pt"), p
        if p.suffix == ".npz":
            with np.load(p, allow_pickle=False) as z:
                for k in z.files:
                    assert z[k].dtype != object


def test_a_bundle_of_the_pickled_format_is_refused_with_advice(bundle):
    _rehash(bundle, lambda m: m.update(format=1))
    with pytest.raises(UserError, match="format 1.*pickle.*rebuild"):
        open_bundle(bundle)


@pytest.mark.parametrize("change, what", [
    (lambda m: m.pop("objects"), "objects"),
    (lambda m: m["objects"][0].pop("diameter"), "diameter"),
    (lambda m: m.update(input_size="abc"), "input_size"),
    (lambda m: m["objects"][0].update(diameter=-102.1), "diameter"),
    (lambda m: m.update(detector="x"), "detector"),
    (lambda m: m["detector"].pop("classes"), "classes"),
    (lambda m: m.update(heads="nope"), "heads"),
])
def test_a_malformed_manifest_is_refused(bundle, change, what):
    _rehash(bundle, change)
    with pytest.raises(UserError, match=f"malformed manifest.*{what}"):
        open_bundle(bundle)


def test_a_manifest_that_misstates_the_latent_size_is_refused(bundle):
    _rehash(bundle, lambda m: m.update(latent_size=64))
    with pytest.raises(UserError, match="encoder gives 128 latent values, the manifest says 64"):
        PoseEstimator(bundle)


def test_decimate_rewrites_the_overlay_meshes_of_a_bundle_that_has_them(bundle):
    from tracker.training.decimate import add_overlay_meshes
    before = open_bundle(bundle).manifest
    assert before.extra["overlay_faces"] != 400 and all(o.overlay_mesh for o in before.objects)
    add_overlay_meshes(bundle, 400, log=lambda *a: None)
    after = open_bundle(bundle).manifest  # verifies every hash again
    assert after.extra["overlay_faces"] == 400
    rel = after.objects[0].overlay_mesh
    assert after.files[rel]["sha256"] != before.files[rel]["sha256"]


def test_a_staged_change_lands_whole_or_not_at_all(bundle):
    from tracker.core.bundle import staged_bundle, write_manifest
    before = sha256(bundle / "manifest.json")
    with pytest.raises(KeyboardInterrupt):
        with staged_bundle(bundle, bundle) as stage:
            (stage / "detector.onnx").write_bytes(b"half written")
            raise KeyboardInterrupt  # Ctrl-C before the manifest is re-hashed
    assert sha256(bundle / "manifest.json") == before
    open_bundle(bundle)  # every hash still matches: the old bundle, untouched
    assert sorted(p.name for p in bundle.parent.iterdir()) == ["lmo"]  # no staging folder left

    with staged_bundle(bundle, bundle) as stage:
        m = open_bundle(stage).manifest.copy()
        m.name = "changed"
        write_manifest(stage, m)
    assert open_bundle(bundle).manifest.name == "changed"
    assert sorted(p.name for p in bundle.parent.iterdir()) == ["lmo"]


def test_the_bundle_writer_hashes_verifies_and_swaps_or_leaves_the_bundle_as_it_was(bundle, monkeypatch):
    from tracker.core import bundle as bmod
    from tracker.core.bundle import bundle_writer
    before = {p.name: sha256(p) for p in bundle.iterdir() if p.is_file()}
    # a failure midway (a file written, the manifest not yet): the old bundle, untouched
    with pytest.raises(RuntimeError, match="midway"):
        with bundle_writer(bundle) as w:
            (w.folder / "codebook.npz").write_bytes(b"half written")
            w.manifest.name = "changed"
            raise RuntimeError("midway")
    # the manifest written, but a file fails its hash on the check before the swap: the same
    real = bmod.write_manifest

    def then_altered(folder, manifest):
        out = real(folder, manifest)
        (folder / "pose_head.json").write_text("{}")
        return out
    monkeypatch.setattr(bmod, "write_manifest", then_altered)
    with pytest.raises(UserError, match="pose_head.json' does not match its SHA-256"):
        with bundle_writer(bundle) as w:
            w.manifest.name = "changed"
    monkeypatch.undo()
    assert {p.name: sha256(p) for p in bundle.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in bundle.parent.iterdir()) == ["lmo"]  # no staging folder left
    open_bundle(bundle)

    # a whole change: a file and the manifest, hashed and swapped in; the writer holds the verified manifest
    with bundle_writer(bundle) as w:
        (w.folder / "notes.txt").write_text("hello")
        w.manifest.name = "changed"
    assert w.manifest.name == "changed" and "notes.txt" in w.manifest.files
    assert open_bundle(bundle).manifest.to_dict() == w.manifest.to_dict()
    # into another folder: the source stays as it was; a new bundle needs a manifest
    with bundle_writer(bundle, bundle.parent / "copy") as w:
        w.manifest.name = "copy"
    assert open_bundle(bundle.parent / "copy").manifest.name == "copy" and open_bundle(bundle).manifest.name == "changed"
    with pytest.raises(ValueError, match="no manifest"):
        with bundle_writer(None, bundle.parent / "new") as w:
            (w.folder / "a.txt").write_text("a")
    assert sorted(p.name for p in bundle.parent.iterdir()) == ["copy", "lmo"]



def test_exact_and_detector_boxes_get_the_manifests_trees_weights(bundle, lmo_dev):
    from tracker.runtime.estimator import Detection
    from tracker.evaluation.evaluate import gt_boxes, gt_instances_with_boxes
    from tracker.core.meshes import load_models
    im = lmo_dev.im_ids[0]
    boxes, _ = gt_boxes(lmo_dev, load_models(bundle / "meshes", sorted({g.obj_id for g in lmo_dev.gt[im]})), [im])
    inst = [(o, b) for o, b, _ in gt_instances_with_boxes(lmo_dev.gt[im], boxes[im], 0.1) if o in (1, 5)]
    img, K = lmo_dev.read_rgb(im), lmo_dev.K(im)

    def poses(exact, weights):
        _rehash(bundle, lambda m: m["heads"].update(trees_weight=weights))
        return PoseEstimator(bundle).estimate(img, K, [Detection(o, b, exact=exact) for o, b in inst])
    a = poses(True, {"exact": 0.5, "detector": 0.0})
    b = poses(False, {"exact": 0.5, "detector": 0.0})
    c = poses(False, {"exact": 0.0, "detector": 0.5})
    for pa, pb, pc in zip(a, b, c):
        assert np.allclose(pa.R, pb.R) and np.allclose(pa.t, pc.t)  # the box's kind picks the weight
        assert not np.allclose(pa.t, pb.t)
    _rehash(bundle, lambda m: m["heads"].update(trees_weight={"detector": 2}))
    with pytest.raises(UserError, match="trees_weight"):
        PoseEstimator(bundle)
