"""The CLI as a user meets it: exit codes and one-line errors, no tracebacks."""
import shutil
import subprocess
import sys
from pathlib import Path


from tests.conftest import REPO
from tracker.core.camera import read_camera

CONVENTION_COMMANDS = ["demo", "track", "calibrate", "synth", "train", "eval", "score", "bench", "imu"]


def run(*args, timeout=300):
    return subprocess.run([sys.executable, str(REPO / "app.py"), *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, cwd=REPO)


def assert_one_line_error(p, code=1):
    assert p.returncode == code, p.stderr
    assert "Traceback" not in p.stderr
    lines = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, p.stderr


def test_help_lists_the_commands():
    p = run("--help")
    assert p.returncode == 0
    for c in CONVENTION_COMMANDS:
        assert f"    {c}" in p.stdout


def test_the_console_script_is_the_same_command_line(tmp_path):
    script = Path(sys.executable).parent / "autopose"  # [project.scripts] in pyproject.toml, by pip install -e .
    assert script.is_file(), f"no {script}: reinstall with pip install --no-deps -e ."
    for args in (["--help"], ["lab"], ["calibrate", "--board", "9x6", "--square", 25, "--out", tmp_path / "c.yaml"],
                 ["no-such-command"]):
        a = run(*args)
        b = subprocess.run([str(script), *map(str, args)], capture_output=True, text=True, timeout=300, cwd=REPO)
        assert (b.returncode, b.stdout, b.stderr) == (a.returncode, a.stdout, a.stderr), args
        assert a.returncode == {"--help": 0, "lab": 2, "calibrate": 1, "no-such-command": 2}[args[0]], a.stderr


def test_join_detectors_bad_input_is_a_one_line_error(tmp_path):
    p = run("lab", "join-detectors", "--model", REPO / "models" / "lmo", "--from", tmp_path, "--out", tmp_path / "j")
    assert_one_line_error(p)
    assert "fuses several networks" in p.stderr  # the shipped detector fuses two (stop 67)
    assert not (tmp_path / "j").exists()


def test_tune_heads_bad_input_is_a_one_line_error(tmp_path):
    p = run("lab", "tune-heads", "--model", REPO / "models" / "lmo", "--data", tmp_path, "--out", tmp_path / "t")
    assert_one_line_error(p)
    assert "no BOP scene folders" in p.stderr and not (tmp_path / "t").exists()
    p = run("lab", "tune-heads", "--model", REPO / "models" / "lmo", "--data", tmp_path, "--weights", "2")
    assert_one_line_error(p)
    assert "[0, 1]" in p.stderr


def test_bad_bundle_and_bad_source_are_one_line_errors(tmp_path, data_dir):
    p = run("track", "--source", data_dir / "lmo" / "dev", "--model", tmp_path / "no-bundle", "--max-frames", 1)
    assert_one_line_error(p)
    assert "model bundle not found" in p.stderr
    p = run("eval", "--model", tmp_path, "--data", data_dir / "lmo" / "dev", "--json", tmp_path / "m.json")
    assert_one_line_error(p)
    assert "manifest.json" in p.stderr
    p = run("lab", "refit-heads", "--model", REPO / "models" / "lmo", "--data", tmp_path, "--out", tmp_path / "b")
    assert_one_line_error(p)
    assert p.stderr.strip() == f"error: {tmp_path}: no synth_config.json; make training data with 'app.py synth'"
    assert not (tmp_path / "b").exists()
    (tmp_path / "empty.mp4").write_bytes(b"")
    for source in ("/dev/video7", tmp_path / "empty.mp4"):  # no OpenCV / FFmpeg log lines before ours
        p = run("track", "--source", source, "--max-frames", 1, "--out", tmp_path / "run")
        assert_one_line_error(p)
        assert p.stderr.strip().startswith("error:") and p.stderr.strip().count("\n") == 0, p.stderr


def test_a_detector_file_altered_or_missing_is_a_one_line_error(tmp_path, data_dir):
    b = tmp_path / "lmo"
    shutil.copytree(REPO / "models" / "lmo", b)
    with open(b / "detector.onnx", "ab") as f:
        f.write(b"\0")
    args = ("--model", b, "--data", data_dir / "lmo" / "dev", "--boxes", "detector", "--max-frames", 1,
            "--json", tmp_path / "m.json")
    p = run("eval", *args)
    assert_one_line_error(p)
    assert "detector.onnx" in p.stderr and "SHA-256" in p.stderr
    (b / "detector.onnx").unlink()
    p = run("track", "--source", data_dir / "lmo" / "dev", "--model", b, "--max-frames", 1, "--out", tmp_path / "r")
    assert_one_line_error(p)
    assert "detector.onnx" in p.stderr and "missing" in p.stderr
    assert not (tmp_path / "m.json").exists()


def test_calibrate_command(data_dir, tmp_path):
    out = tmp_path / "cam.yml"
    p = run("calibrate", "--images", data_dir / "calib_opencv" / "left*.jpg", "--board", "9x6",
            "--square", 25, "--out", out)
    assert p.returncode == 0, p.stderr
    assert "RMS re-projection error" in p.stdout
    cam = read_camera(out)
    assert cam.size == (640, 480) and 530 < cam.K[0, 0] < 542


def test_calibrate_errors(tmp_path, data_dir):
    assert_one_line_error(run("calibrate", "--images", tmp_path / "*.jpg", "--board", "9x6", "--square", 25,
                              "--out", tmp_path / "c.yml"))
    assert_one_line_error(run("calibrate", "--images", data_dir / "calib_opencv" / "left*.jpg",
                              "--board", "9by6", "--square", 25, "--out", tmp_path / "c.yml"))
    assert_one_line_error(run("calibrate", "--source", tmp_path / "nope.mp4", "--board", "9x6", "--square", 25,
                              "--out", tmp_path / "c.yml"))


def test_preview_on_a_broken_scene(tmp_path, data_dir):
    (tmp_path / "rgb").mkdir()
    p = run("lab", "preview", "--data", tmp_path, "--models", data_dir / "lmo" / "models")
    assert_one_line_error(p)
    assert "scene_camera.json" in p.stderr


def test_models_info_command(tmp_path, data_dir):
    models = tmp_path / "models"
    models.mkdir()
    (models / "obj_000001.ply").symlink_to(data_dir / "lmo" / "models" / "obj_000001.ply")
    p = run("lab", "models-info", "--models", models, "--out", tmp_path / "models_info.json")
    assert p.returncode == 0, p.stderr
    assert "obj 1: diameter 102.10 mm, 0 discrete symmetries" in p.stdout


def test_demo_runs_the_bundled_model_through_the_tracker(tmp_path):
    assert (REPO / "models" / "lmo" / "manifest.json").is_file(), "the lmo bundle ships with the repo"
    p = run("demo", "--out", tmp_path / "run", "--max-frames", 3)
    assert p.returncode == 0, p.stderr
    for f in ("poses.csv", "timings.csv", "summary.json", "recording.rrd"):
        assert (tmp_path / "run" / f).is_file(), f
    assert "accuracy against the ground truth" in p.stdout and "rerun recording" in p.stdout


def test_numeric_flags_are_checked_before_any_work(tmp_path, data_dir):
    dev = data_dir / "lmo" / "dev"
    for args in (["eval", "--model", "models/lmo", "--data", dev, "--json", tmp_path / "m.json", "--max-frames", 0],
                 ["track", "--source", dev, "--detect-every", 0],
                 ["train-detector", "--data", tmp_path, "--model", "models/lmo", "--minutes", -5],
                 ["lab", "pack-scene", "--data", dev, "--out", tmp_path / "r", "--quality", 200],
                 ["calibrate", "--images", "x", "--board", "9x6", "--square", "nan", "--out", tmp_path / "c.yaml"],
                 ["synth", "--models", tmp_path, "--out", tmp_path / "s", "--images", 2, "--obj-ids", "1,abc"],
                 ["synth", "--models", tmp_path, "--out", tmp_path / "s", "--images", 2, "--seed", -5]):
        p = run(*args)
        assert p.returncode == 2 and "Traceback" not in p.stderr, (args, p.stderr)
        assert "error: argument" in p.stderr, p.stderr


def test_a_name_that_is_not_utf8_is_a_one_line_error_not_a_crash(tmp_path, data_dir):
    """OpenCV crashes the process (a segfault) on a path whose bytes are not UTF-8."""
    latin1 = tmp_path / "vid\udce9o.avi"  # the bytes b"vid\xe9o.avi", as Python keeps them
    shutil.copy(REPO / "demo" / "lmo_dev" / "rgb.avi", latin1)
    p = run("track", "--source", latin1, "--max-frames", 1, "--rerun", "off", "--out", tmp_path / "run")
    assert_one_line_error(p)
    assert "the name is not UTF-8" in p.stderr and "vid\\udce9o.avi" in p.stderr
    folder = tmp_path / "frames"
    folder.mkdir()
    shutil.copy(data_dir / "lmo" / "dev" / "rgb" / "000003.png", folder / "\udce9t\udce9.png")
    p = run("track", "--source", folder, "--calib", REPO / "calib" / "lmo_kinect.yml", "--max-frames", 1,
            "--rerun", "off", "--out", tmp_path / "run2")
    assert_one_line_error(p)
    assert "image " in p.stderr and "the name is not UTF-8" in p.stderr


def test_an_unwritable_output_is_a_one_line_error(tmp_path, data_dir):
    (tmp_path / "taken").write_text("a file, not a folder")
    p = run("lab", "pack-scene", "--data", data_dir / "lmo" / "dev", "--out", tmp_path / "taken" / "rec")
    assert_one_line_error(p)
    assert "Not a directory" in p.stderr and "taken" in p.stderr


def test_outputs_that_cannot_be_written_are_refused_before_the_work(tmp_path, data_dir):
    import shutil
    dev = tmp_path / "dev"  # a copy: the guard under test is what keeps pack-scene out of the scene
    shutil.copytree(data_dir / "lmo" / "dev", dev)
    (tmp_path / "folder").mkdir()
    for args, said in (
            (["eval", "--model", "models/lmo", "--data", dev, "--json", tmp_path / "folder"], "is a folder"),
            (["score", "--results", tmp_path / "r.csv", "--data", dev, "--models", "models/lmo/meshes",
              "--json", tmp_path / "folder"], "is a folder"),
            (["synth", "--models", data_dir / "lmo" / "models", "--out", tmp_path / "s", "--images", 2,
              "--preview", tmp_path / "folder"], "name a .png or .jpg"),
            (["lab", "pack-scene", "--data", dev, "--out", dev], "is the scene itself"),
            (["lab", "resize-scene", "--data", dev, "--out", dev, "--size", 320, 240], "is the scene itself")):
        p = run(*args, timeout=60)
        assert_one_line_error(p)
        assert said in p.stderr, p.stderr
    assert not (tmp_path / "s").exists() and not (dev / "rgb.avi").exists()


def test_empty_ground_truth_and_missing_ablate_tables_are_clear_errors(tmp_path, data_dir):
    import shutil

    import pytest

    from tracker.core.errors import UserError
    from tracker.evaluation.evaluate import evaluate
    from tracker.evaluation.report import build_report
    scene = tmp_path / "scene"
    (scene / "rgb").mkdir(parents=True)
    shutil.copy(data_dir / "lmo" / "dev" / "rgb" / "000003.png", scene / "rgb")
    shutil.copy(data_dir / "lmo" / "dev" / "scene_camera.json", scene)
    (scene / "scene_gt.json").write_text("{}")
    with pytest.raises(UserError, match="lists no images"):
        evaluate(REPO / "models" / "lmo", scene, tmp_path / "m.json", progress=False)
    with pytest.raises(UserError, match="file not found"):
        build_report(REPO / "models" / "lmo", scene, tmp_path / "report", ablate_json=tmp_path / "nope.json")
    (tmp_path / "bad.json").write_text('{"train": 1}')
    with pytest.raises(UserError, match="missing validation"):
        build_report(REPO / "models" / "lmo", scene, tmp_path / "report", ablate_json=tmp_path / "bad.json")


def test_track_on_a_scene_with_objects_the_bundle_does_not_know(tmp_path, data_dir):
    import json
    import shutil

    import pytest

    from tracker.core.errors import UserError
    from tracker.evaluation.track import track
    from tracker.runtime.loop import TrackConfig
    dev = data_dir / "lmo" / "dev"
    scene = tmp_path / "scene"
    (scene / "rgb").mkdir(parents=True)
    shutil.copy(dev / "rgb" / "000003.png", scene / "rgb")
    cam = json.loads((dev / "scene_camera.json").read_text())["3"]
    gt = json.loads((dev / "scene_gt.json").read_text())["3"]
    gt[0]["obj_id"] = 99
    (scene / "scene_camera.json").write_text(json.dumps({"3": cam}))
    (scene / "scene_gt.json").write_text(json.dumps({"3": gt}))
    with pytest.raises(UserError, match=r"object\(s\) \[99\].*--boxes detector"):
        track(TrackConfig(str(scene), str(REPO / "models" / "lmo"), tmp_path / "run", overlay=False),
                  log=lambda m: None)


def test_every_command_and_lab_tool_has_a_help_page_that_renders():
    """argparse formats help strings with %: a stray '%' breaks only that page, at run time."""
    import argparse
    from tracker.cli.main import build_parser

    def subparsers(p):
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                yield from a.choices.items()
    n = 0
    for name, sp in subparsers(build_parser()):
        assert sp.format_help(), name
        n += 1
        for lab_name, lp in subparsers(sp):
            assert lp.format_help(), lab_name
            n += 1
    assert n >= 25  # 12 commands, lab and its tools
