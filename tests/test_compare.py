"""``eval --per-instance`` and ``lab compare``: per-instance rows that add up to the metrics JSON,
and the paired bootstrap on hand-made files whose difference is known."""
import csv
import json

import numpy as np
import pytest

from tests.conftest import REPO
from tracker.core.errors import UserError
from tracker.evaluation.compare import compare_files, compare_rows


def _rows(n_frames, per_frame, add=0.0, mssd=0.0, mspd=0.0):
    """Instances of ``n_frames`` frames, ``per_frame`` each; each value a constant or a function of the frame."""
    val = lambda v, f: v(f) if callable(v) else v  # noqa: E731
    return [{"im_id": f, "gt_index": g, "obj_id": g + 1, "add_pass": val(add, f), "mssd_recall": val(mssd, f),
             "mspd_recall": val(mspd, f)} for f in range(n_frames) for g in range(per_frame)]


def _write(path, rows):
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return path


def test_a_uniform_gain_is_exact_and_kept(tmp_path):
    a = _write(tmp_path / "a.csv", _rows(30, 3, add=0, mssd=0.2, mspd=0.5))
    b = _write(tmp_path / "b.csv", _rows(30, 3, add=1, mssd=0.3, mspd=0.5))
    r = compare_files(a, b, n_boot=2000)
    f = r["figures"]
    assert f["add_recall"]["diff"] == pytest.approx(1.0) and f["add_recall"]["ci"] == pytest.approx([1.0, 1.0])
    assert f["ar_mssd"]["diff"] == pytest.approx(0.1) and f["ar_mspd"]["ci"] == pytest.approx([0.0, 0.0])
    assert f["mean"]["diff"] == pytest.approx(1.1 / 3)
    assert r["verdict"]["keep_b"] and r["n_frames"] == 30 and r["n_instances"] == 90


def test_the_command_writes_the_comparison_and_prints_the_verdict(tmp_path):
    import subprocess
    import sys
    a = _write(tmp_path / "a.csv", _rows(30, 3, add=0, mssd=0.2, mspd=0.5))
    b = _write(tmp_path / "b.csv", _rows(30, 3, add=1, mssd=0.3, mspd=0.5))
    run = lambda *args: subprocess.run([sys.executable, str(REPO / "app.py"), "lab", "compare", *map(str, args)],  # noqa: E731
                                       capture_output=True, text=True, timeout=300, cwd=REPO)
    p = run(a, b, "--json", tmp_path / "c.json", "--bootstrap", 500)
    assert p.returncode == 0, p.stderr
    r = json.loads((tmp_path / "c.json").read_text())
    assert r["figures"]["add_recall"]["diff"] == pytest.approx(1.0) and r["verdict"]["keep_b"]
    assert "keep B" in p.stdout and "wrote" in p.stdout
    p = run(a, tmp_path / "nope.csv", "--json", tmp_path / "d.json")
    assert p.returncode != 0 and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "d.json").exists()


def test_a_gain_in_half_the_frames_has_an_interval_around_it():
    a = _rows(200, 2)
    b = _rows(200, 2, add=lambda f: float(f % 2), mssd=lambda f: float(f % 2), mspd=lambda f: float(f % 2))
    r = compare_rows(a, b, n_boot=4000)
    lo, hi = r["figures"]["add_recall"]["ci"]
    assert r["figures"]["add_recall"]["diff"] == pytest.approx(0.5)
    # 200 frames of a fair coin: standard error 0.035, so the 95 % interval is about 0.43 .. 0.57
    assert 0.40 < lo < 0.47 and 0.53 < hi < 0.60
    assert r["verdict"]["keep_b"]


def test_a_figure_that_falls_vetoes_a_gain_on_the_mean():
    a = _rows(100, 2, add=1.0, mssd=0.0, mspd=0.0)
    b = _rows(100, 2, add=0.8, mssd=1.0, mspd=1.0)   # mean +0.6, ADD(I) -0.2 in every frame
    r = compare_rows(a, b, n_boot=1000)
    assert r["figures"]["mean"]["ci"][0] > 0
    assert r["verdict"] == {**r["verdict"], "keep_b": False, "falls": ["add_recall"]}


def test_no_difference_is_not_kept():
    rng = np.random.default_rng(0)
    rows = _rows(50, 3)
    for r in rows:
        r["add_pass"] = float(rng.random() < 0.3)
    r = compare_rows(rows, [dict(x) for x in rows], n_boot=500)
    assert r["figures"]["mean"]["ci"] == [0.0, 0.0] and not r["verdict"]["keep_b"]


def test_files_of_other_instances_or_columns_are_refused(tmp_path):
    a = _write(tmp_path / "a.csv", _rows(5, 2))
    b = _write(tmp_path / "b.csv", _rows(6, 2))
    with pytest.raises(UserError, match="different instances.*im_id 5"):
        compare_files(a, b)
    bad = tmp_path / "bad.csv"
    bad.write_text("im_id,obj_id\n1,2\n")
    with pytest.raises(UserError, match="no column"):
        compare_files(a, bad)
    with pytest.raises(UserError, match="no such per-instance file"):
        compare_files(a, tmp_path / "none.csv")
    rows = _rows(5, 2)
    rows[3]["add_pass"] = float("nan")  # would make every interval NaN and the JSON invalid
    with pytest.raises(UserError, match="line 5: add_pass is nan"):
        compare_files(a, _write(tmp_path / "nan.csv", rows))
    (tmp_path / "bin.csv").write_bytes(bytes(range(256)))
    with pytest.raises(UserError, match="not a text CSV"):
        compare_files(a, tmp_path / "bin.csv")
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + a.read_bytes())  # a spreadsheet's "CSV UTF-8"
    assert compare_files(a, tmp_path / "bom.csv")["figures"]["mean"]["diff"] == 0.0


def test_eval_per_instance_rows_add_up_to_its_metrics(data_dir, tmp_path):
    from tracker.evaluation.evaluate import evaluate
    m = evaluate(REPO / "models" / "lmo", data_dir / "lmo" / "dev", tmp_path / "m.json", boxes="gt", max_frames=3,
                 progress=False, per_instance=tmp_path / "inst.csv")
    with open(tmp_path / "inst.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == m["n_gt"] > 10
    mean = lambda c: np.mean([float(r[c]) for r in rows])  # noqa: E731
    assert mean("add_pass") == pytest.approx(m["add_recall"])
    assert mean("mssd_recall") == pytest.approx(m["ar_mssd"], abs=1e-4)
    assert mean("mspd_recall") == pytest.approx(m["ar_mspd"], abs=1e-4)
    # the per-threshold columns are what the recalls are made of
    assert mean("mspd_pass@5") == pytest.approx(m["recall_mspd"][0])
    assert json.loads((tmp_path / "m.json").read_text())["per_instance"] == str(tmp_path / "inst.csv")
    r = compare_files(tmp_path / "inst.csv", tmp_path / "inst.csv", n_boot=200)
    assert r["figures"]["ar_mspd"]["diff"] == 0.0 and r["n_frames"] == 3
