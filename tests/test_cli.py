"""The CLI as a user meets it: exit codes and one-line errors, no tracebacks."""
import subprocess
import sys


from tests.conftest import REPO
from tracker.camera import read_camera

CONVENTION_COMMANDS = ["demo", "track", "calibrate", "synth", "train", "eval", "score", "bench", "imu"]


def run(*args, timeout=300):
    return subprocess.run([sys.executable, str(REPO / "app.py"), *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, cwd=REPO)


def assert_one_line_error(p, code=1):
    assert p.returncode == code, p.stderr
    assert "Traceback" not in p.stderr
    lines = [l for l in p.stderr.splitlines() if l.startswith("error:")]
    assert len(lines) == 1, p.stderr


def test_help_lists_the_commands():
    p = run("--help")
    assert p.returncode == 0
    for c in CONVENTION_COMMANDS:
        assert f"    {c}" in p.stdout


def test_bad_bundle_and_bad_source_are_one_line_errors(tmp_path, data_dir):
    p = run("track", "--source", data_dir / "lmo" / "dev", "--model", tmp_path / "no-bundle", "--max-frames", 1)
    assert_one_line_error(p)
    assert "model bundle not found" in p.stderr
    p = run("eval", "--model", tmp_path, "--data", data_dir / "lmo" / "dev", "--json", tmp_path / "m.json")
    assert_one_line_error(p)
    assert "manifest.json" in p.stderr
    p = run("refit-heads", "--model", REPO / "models" / "lmo", "--data", tmp_path, "--out", tmp_path / "b")
    assert_one_line_error(p)
    assert "synth_config.json" in p.stderr or "train" in p.stderr  # no training data (or no torch)
    assert not (tmp_path / "b").exists()


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
    p = run("preview", "--data", tmp_path, "--models", data_dir / "lmo" / "models")
    assert_one_line_error(p)
    assert "scene_camera.json" in p.stderr


def test_models_info_command(tmp_path, data_dir):
    models = tmp_path / "models"
    models.mkdir()
    (models / "obj_000001.ply").symlink_to(data_dir / "lmo" / "models" / "obj_000001.ply")
    p = run("models-info", "--models", models, "--out", tmp_path / "models_info.json")
    assert p.returncode == 0, p.stderr
    assert "obj 1: diameter 102.10 mm, 0 discrete symmetries" in p.stdout


def test_demo_runs_the_bundled_model_through_the_tracker(tmp_path):
    assert (REPO / "models" / "lmo" / "manifest.json").is_file(), "the lmo bundle ships with the repo"
    p = run("demo", "--out", tmp_path / "run", "--max-frames", 3)
    assert p.returncode == 0, p.stderr
    for f in ("poses.csv", "timings.csv", "summary.json", "recording.rrd"):
        assert (tmp_path / "run" / f).is_file(), f
    assert "accuracy against the ground truth" in p.stdout and "rerun recording" in p.stdout
