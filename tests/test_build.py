"""app.py build: meshes -> a bundle in one budget, stage by stage, cached, resumable, its
recipe in the manifest. A tiny budget and tiny splits: this exercises the job, not accuracy."""
import dataclasses
import json
import os
import shutil
from pathlib import Path

import pytest

pytest.importorskip("torch")
from tracker.training import build as bb  # noqa: E402
from tracker.core.bundle import open_bundle  # noqa: E402
from tracker.core.errors import UserError  # noqa: E402
from tests.conftest import FakeClock, fixture_meshes as _meshes  # noqa: E402

FIX = Path(__file__).parent / "fixtures" / "models"




def test_the_budget_is_split_by_the_documented_rule():
    p = bb.plan(bb.Recipe(models="m", minutes=100), ram_bytes=1e12)  # memory to spare: time decides
    # the heads' 10 %: three head sets of three regressors' worth each
    assert p["encoder_minutes"] == 38 and p["detector_minutes"] == 30 and p["reg_minutes"] == pytest.approx(10 / 9, abs=1e-3)
    assert bb.plan(bb.Recipe(models="m", minutes=100, head_sets=1))["reg_minutes"] == pytest.approx(10 / 3, abs=1e-3)
    assert p["render_seconds"] == p["render_det_seconds"] == 0.10 * 100 * 60
    assert p["render_images"] == p["render_det_images"] == int(0.10 * 100 * 60 * bb.MAX_RATE)
    assert sum(bb.SHARES.values()) == pytest.approx(1.0)


def test_the_splits_are_capped_by_memory_and_their_unused_time_goes_to_training():
    """A long budget would render more images than the machine can train on (an 8-object build
    of 8 h: ~90 k per split against ~16 k that 24 GB hold): the splits stop at the memory's cap,
    and the time they leave goes to the three training stages in proportion to their shares."""
    cap24 = bb.memory_cap(64, 24e9)
    assert 10_000 < cap24 < 20_000  # 0.75 x 24 GB over ~1.1 MB a pair of images
    assert bb.memory_cap(64, 48e9) > 2 * cap24 and bb.memory_cap(128, 24e9) < cap24 / 3  # 4x the bytes a crop
    assert bb.memory_cap(32, 24e9) == bb.memory_cap(16, 24e9)  # small crops: the detector's images bound it
    p = bb.plan(bb.Recipe(models="m", minutes=480), ram_bytes=24e9)
    assert p["render_images"] == p["render_det_images"] == cap24 == p["max_images"]
    assert bb.plan(bb.Recipe(models="m", minutes=30), ram_bytes=24e9)["render_images"] == int(0.1 * 30 * 60 * bb.MAX_RATE)
    assert bb.plan(bb.Recipe(models="m", minutes=480, max_images=500), ram_bytes=24e9)["render_images"] == 500
    q = bb.share_out(p, 480, 2 * 30 * 60)  # both splits done in 18 of their 48 min: 60 min left over
    train = ("encoder_minutes", "reg_minutes", "detector_minutes")
    assert all(q[k] > p[k] for k in train)
    assert q["encoder_minutes"] / q["detector_minutes"] == pytest.approx(p["encoder_minutes"] / p["detector_minutes"], rel=1e-3)
    used = q["encoder_minutes"] + 3 * 3 * q["reg_minutes"] + q["detector_minutes"]  # three sets, three regressors each
    assert used == pytest.approx(p["encoder_minutes"] + 9 * p["reg_minutes"] + p["detector_minutes"] + 60, abs=0.01)
    assert bb.share_out(p, 480, 0) == p and bb.share_out(p, 480, -5) == p  # a split over its time takes nothing
    # what the render stages recorded: only a split that stopped at its count leaves time
    st = lambda s, limited: {"seconds": s, **({} if limited is None else {"time_limited": limited})}  # noqa: E731
    share = p["render_seconds"]
    assert bb.leftover_seconds(p, {"render": st(600, False), "render-det": st(700, False)}) == 2 * share - 1300
    assert bb.leftover_seconds(p, {"render": st(600, False), "render-det": st(share, True)}) == share - 600
    assert bb.leftover_seconds(p, {"render": st(600, None), "render-det": st(share + 50, False)}) == 0  # older; over
    assert bb.Recipe.from_dict({"models": "m"}).max_images is None
    with pytest.raises(UserError, match="--max-images must be"):
        bb.build(bb.Recipe(models=str(FIX), max_images=0), "/nonexistent/out", log=lambda m: None)


def test_the_encoder_stage_reserves_time_for_its_crops_and_heads():
    """train_bundle inside build: the autoencoder gets what is left of the stage after the
    crops, the regressors and the work after training (the stage ran 4.6 min over before)."""
    from tracker.training import train as tr
    assert tr.training_minutes(100.0, 25.0, 1.0, 1000, 0.8, False) == 25.0  # room to spare: as asked
    n = 45_616
    got = tr.training_minutes(27.6, 25.2, 1.13, n, 0.8, False)
    after = 3 * 0.8 + n * (tr.CUT_S_PER_CROP + tr.AFTER_S_PER_CROP) / 60
    assert got == pytest.approx(27.6 - 1.13 - after) and got < 25.2
    assert tr.training_minutes(27.6, 25.2, 1.13, n, 0.8, True) > got  # the exact crops already cut: less to reserve
    assert tr.training_minutes(27.6, 25.2, 1.13, n, 0.8, False, head_sets=3) == pytest.approx(got - 6 * 0.8)
    assert tr.training_minutes(5.0, 25.0, 1.0, n, 0.8, False) == tr.MIN_TRAIN_MINUTES  # never nothing
    assert tr.training_minutes(5.0, 0.01, 1.0, n, 0.8, False) == 0.01  # never more than asked


def test_recipes_recorded_before_decimated_renders_keep_the_full_meshes():
    """A manifest's recipe from before synth decimated by default redoes the full meshes."""
    old = {"models": "m", "minutes": 60.0, "seed": 3}
    assert bb.Recipe.from_dict(old).mesh_faces == 0
    assert bb.Recipe.from_dict({**old, "mesh_faces": 4000}).mesh_faces == 4000
    assert bb.Recipe(models="m").mesh_faces == 4000
    assert bb.Recipe.from_dict(old).head_sets == 1 and bb.Recipe(models="m").head_sets == 3  # one set before stop 51
    # the COCO-pretrained detector since stop 57; a recipe recorded before it keeps the plain one
    assert bb.Recipe.from_dict(old).detector_backbone == "plain" and bb.Recipe(models="m").detector_backbone == "nanodet"
    # NanoDet at 416 x 320 stored int8 since stop 66; a recipe recorded before it keeps 320 x 240 float32
    before = bb.Recipe.from_dict(old)
    assert (before.detector_input, before.detector_int8) == ([320, 240], False)
    assert (bb.Recipe(models="m").detector_input, bb.Recipe(models="m").detector_int8) == ([416, 320], True)
    # ... and its detector stage keeps the key it was cached under then (the input and int8 were not in it)
    assert bb.detector_key(before, "e", "r", 50.0) == bb._key("detector", "e", "r", 50.0, "plain", 3)
    assert len({bb.detector_key(dataclasses.replace(before, **c), "e", "r", 50.0)
                for c in ({}, {"detector_input": [416, 320]}, {"detector_int8": True})}) == 3


def test_build_makes_a_bundle_resumes_and_records_its_recipe(small, tmp_path, monkeypatch):
    src = _meshes(tmp_path)
    out = tmp_path / "models" / "mine"
    recipe = bb.Recipe(models=str(src), minutes=0.05, workers=1, size=32, latent=16)
    # the stages' times from a clock of the test's own: it moves only where the test says, so the
    # times recorded are known exactly (no sleeping, whatever the machine's load)
    clock = FakeClock()
    monkeypatch.setattr(bb, "time", clock.module_time())
    # an interruption while the detector trains, 30 s into it: what was done before is kept
    import tracker.training.detector_train as dt
    real = dt.train_detector

    def interrupted(*a, **k):
        clock.advance(30.0)
        raise KeyboardInterrupt
    monkeypatch.setattr(dt, "train_detector", interrupted)
    logs = []
    with pytest.raises(KeyboardInterrupt):
        bb.build(recipe, out, log=logs.append)
    state = json.loads((tmp_path / "models" / "mine.work" / "build" / "state.json").read_text())
    assert [k for k in state if state[k]["done"]] == ["models", "render", "render-det", "encoder"]
    assert not state["detector"]["done"] and state["detector"]["seconds"] == 30.0  # its time so far is kept

    def resumed(*a, **k):  # 12 s more in the second run
        clock.advance(12.0)
        return real(*a, **k)
    monkeypatch.setattr(dt, "train_detector", resumed)
    logs = []
    s = bb.build(recipe, out, log=logs.append)
    assert sum("done before (cached)" in m for m in logs) == 4  # the same command went on where it stopped
    # the detector's time adds up both runs, and so does the whole build's
    assert s["stages"]["detector"]["seconds"] == 42.0
    monkeypatch.setattr(dt, "train_detector", real)
    after = json.loads((tmp_path / "models" / "mine.work" / "build" / "state.json").read_text())
    assert s["minutes_all_runs"] == round(sum(v["seconds"] for v in after.values()) / 60, 1)
    b = open_bundle(out)  # verified: every file hashed, the report too
    assert b.manifest.has_detector and sorted(b.manifest.obj_ids) == [1, 2]
    # the recipe's detector: trained at 416 x 320, stored int8 (7-bit weights) calibrated on the renders
    # it trained on
    d = b.manifest.detector
    assert (d["input_w"], d["input_h"]) == (416, 320) and d["int8"]["calibration_data"].endswith("split_all")
    assert "7 bits" in d["int8"]["method"]
    import onnx
    assert "QuantizeLinear" in {n.op_type for n in onnx.load(str(b.path("detector"))).graph.node}
    assert "416 x 320 int8" in (out / "report" / "report.md").read_text()
    assert b.manifest.heads["ensemble"]["seeds"] == [0, 1, 2]  # three head sets averaged
    from tracker.runtime.heads import HeadEnsemble, load_bundle_head
    assert isinstance(load_bundle_head(b), HeadEnsemble) and len(load_bundle_head(b).members) == 3
    assert "report/report.md" in b.manifest.files and "report/samples.png" in b.manifest.files
    text = (out / "report" / "report.md").read_text()
    assert "On held-out renders" in text and "| detector |" in text
    assert set(s["stages"]["check"]) >= {"gt", "detector"}
    assert not any(p.name.startswith("split") for p in out.iterdir())  # intermediates stay in the work folder
    notes = []
    again = bb.recipe_from_manifest(out, log=notes.append)
    assert again == recipe and notes == []  # every artefact is the build's own: nothing to say
    for f in src.iterdir():  # the same meshes with new times (a fresh copy): still nothing to redo
        os.utime(f, (f.stat().st_atime + 3600, f.stat().st_mtime + 3600))
    logs = []
    bb.build(again, out, log=logs.append)  # --from-manifest on a finished build: nothing to redo
    assert sum("done before (cached)" in m for m in logs) == 7
    from tracker.core.bundle import update_manifest

    def other_heads(manifest, folder):  # as refit-heads or join-heads would leave it
        (folder / "pose_head.json").write_text((folder / "pose_head.json").read_text() + "\n")
    update_manifest(out, other_heads)
    bb.recipe_from_manifest(out, log=notes.append)
    assert len(notes) == 1 and "'s pose_head came from another run than its build" in notes[0], notes
    # a detector fused with another run's (lab fuse-detectors) is said too; the rebuild below
    # trains its own detector in its place, and the fused network goes with the old one
    from tracker.training.detector_fusion import fuse_detectors
    shutil.copytree(out, tmp_path / "twin")
    fuse_detectors(out, [tmp_path / "twin"], log=lambda *a: None)
    notes.clear()
    bb.recipe_from_manifest(out, log=notes.append)
    assert "'s detector_2, pose_head came from another run" in notes[0], notes
    assert "fused with 1 more network(s)" in notes[0], notes
    # another seed renders new splits into the same folders: what was cut from the old ones and
    # the old detector's checkpoint are removed (gigabytes at full size), never loaded or resumed
    work = tmp_path / "models" / "mine.work"
    old = {p.name for p in work.iterdir() if p.name.startswith(("crops_", "det_images_", "detector_ckpt_"))}
    assert {n.split("_")[0] for n in old} == {"crops", "det", "detector"}
    logs = []
    bb.build(dataclasses.replace(recipe, seed=1), out, log=logs.append)
    removed = " ".join(m for m in logs if m.startswith("removed"))
    assert all(n in removed for n in old), (old, removed)
    assert not any(m.startswith(("loaded", "resumed from")) for m in logs), logs
    assert len(list(work.glob("det_images_*.npz"))) == len(list(work.glob("detector_ckpt_*.pt"))) == 1
    rebuilt = open_bundle(out).manifest
    assert "fusion" not in rebuilt.detector and "detector_2" not in rebuilt.artefacts
    assert not (out / "detector_2.onnx").exists()


def test_build_refuses_bad_input_in_one_line(small, tmp_path):
    with pytest.raises(UserError, match="not a folder of meshes"):
        bb.build(bb.Recipe(models=str(tmp_path / "nope"), minutes=0.05), tmp_path / "out", log=lambda m: None)
    assert not (tmp_path / "out.work").exists()
    src = _meshes(tmp_path)
    with pytest.raises(UserError, match="--objects 7"):
        bb.build(bb.Recipe(models=str(src), minutes=0.05, objects=[1, 7]), tmp_path / "out2", log=lambda m: None)
    with pytest.raises(UserError, match="--head-sets must be"):
        bb.build(bb.Recipe(models=str(src), minutes=0.05, head_sets=0), tmp_path / "out3", log=lambda m: None)
    for wh in ([417, 320], [416], [32, 32]):
        with pytest.raises(UserError, match="--detector-input must be"):
            bb.build(bb.Recipe(models=str(src), minutes=0.05, detector_input=wh), tmp_path / "out3",
                     log=lambda m: None)
    for encoder, size, step in (("plain", 70, 16), ("lite0", 48, 32)):  # before any rendering
        with pytest.raises(UserError, match=f"--encoder {encoder} takes crops a multiple of {step} pixels"):
            bb.build(bb.Recipe(models=str(src), minutes=0.05, encoder=encoder, size=size), tmp_path / "out4",
                     log=lambda m: None)
        assert not (tmp_path / "out4.work").exists()
    bare = tmp_path / "bare"  # a bundle made by 'train', not 'build'
    shutil.copytree(Path(__file__).parents[1] / "models" / "lmo", bare)
    from tracker.core.bundle import update_manifest
    update_manifest(bare, lambda m, folder: m.extra.pop("build"))
    with pytest.raises(UserError, match="no build recipe"):
        bb.recipe_from_manifest(bare)


def test_the_shipped_bundle_records_the_one_command_that_built_it():
    r = bb.recipe_from_manifest(Path(__file__).parents[1] / "models" / "lmo")  # docs/models.md's command
    assert (r.models, r.minutes, r.objects, r.seed) == ("../shared/data/lmo/models", 480.0, None, 0)


@pytest.mark.parametrize("change, match", [
    (lambda r: r.update(minutes="ten"), "'minutes' must be a positive number"),
    (lambda r: r.update(models=None), "'models' must name the meshes' folder"),
    (lambda r: r.update(seed=-1), "'seed' must be a whole number"),
    (lambda r: r.update(objects=[0]), "'objects' must be a list of object ids"),
    (lambda r: r.update(encoder=3), "'encoder' must be text"),
    (lambda r: r.update(detector_input=[416, "320"]), "'detector_input' must be two whole numbers"),
    (lambda r: r.update(detector_int8="yes"), "'detector_int8' must be true or false"),
])
def test_a_hand_edited_recipe_is_one_line_error(tmp_path, change, match):
    b = tmp_path / "b"
    shutil.copytree(Path(__file__).parents[1] / "models" / "lmo", b)
    from tracker.core.bundle import update_manifest
    update_manifest(b, lambda m, folder: change(m.extra["build"]["recipe"]))
    with pytest.raises(UserError, match=f"build recipe is malformed \\({match}"):
        bb.recipe_from_manifest(b)


def test_from_manifest_refuses_the_options_it_would_ignore(tmp_path):
    """The recorded recipe is what --from-manifest builds: a --minutes or --models beside it would
    be silently overruled (a 480-minute rebuild of models/lmo asked for as 0.5 minutes)."""
    from tests.test_cli import assert_one_line_error, run
    p = run("build", "--from-manifest", "models/lmo", "--out", tmp_path / "x", "--minutes", 0.5, "--seed", 7)
    assert_one_line_error(p)
    assert "drop --minutes, --seed" in p.stderr and not (tmp_path / "x").exists()


def test_build_without_the_train_extra_stops_before_rendering(small, tmp_path, monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, "torch", None)  # 'import torch' fails, as without the extra
    with pytest.raises(UserError, match=r"the 'train' extra: .*pip install -e '\.\[train\]'"):
        bb.build(bb.Recipe(models=str(_meshes(tmp_path)), minutes=0.05), tmp_path / "out", log=lambda m: None)
    assert not (tmp_path / "out.work").exists() and not (tmp_path / "out").exists()


def test_sigterm_ends_a_long_job_as_ctrl_c_does():
    import signal
    from tracker.runtime.signals import sigterm_as_ctrl_c
    old = signal.getsignal(signal.SIGTERM)
    after = []
    try:
        sigterm_as_ctrl_c()
        with pytest.raises(KeyboardInterrupt):
            # the signal to this thread, its Python handler run before raise_signal returns: no
            # waiting for it to arrive
            signal.raise_signal(signal.SIGTERM)
            after.append("went on")  # the job's next line never runs
        assert after == []
    finally:
        signal.signal(signal.SIGTERM, old)


def test_build_takes_object_names_from_a_names_file_and_its_recipe_keeps_them(small, tmp_path, monkeypatch):
    src = _meshes(tmp_path)
    names = tmp_path / "names.json"
    names.write_text(json.dumps({"2": "mug"}))
    r = bb.Recipe(models=str(src), minutes=0.05, names=str(names))  # a names file is read into the recipe
    assert r.names == {"2": "mug"}
    assert bb.Recipe.from_dict(json.loads(json.dumps(dataclasses.asdict(r)))) == r  # build --from-manifest
    assert bb.Recipe(models=str(src), names={10: "b", 9: "a"}).names == {"9": "a", "10": "b"}
    from tracker.training.synth import engine

    def stop(*args, **kw):  # the first stage is all this needs
        raise KeyboardInterrupt
    monkeypatch.setattr(engine, "generate", stop)
    with pytest.raises(KeyboardInterrupt):
        bb.build(r, tmp_path / "out", log=lambda m: None)
    state = json.loads((tmp_path / "out.work" / "build" / "state.json").read_text())
    assert state["models"]["objects"] == {"1": "obj_1", "2": "mug"}  # given names beat the file names
    assert json.loads((tmp_path / "out.work" / "build" / "models" / "names.json").read_text()) == {"1": "obj_1",
                                                                                                   "2": "mug"}
    names.write_text('{"2": "mug"')
    with pytest.raises(UserError, match=r"names.json: not valid JSON"):
        bb.Recipe(models=str(src), names=str(names))
    with pytest.raises(UserError, match=r"--names: names for object\(s\) 5"):
        bb.build(bb.Recipe(models=str(src), minutes=0.05, names={5: "x"}), tmp_path / "out2", log=lambda m: None)
