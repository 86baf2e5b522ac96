#!/usr/bin/env python3
"""Put the detector of commit 2ab33ed's models/lmo (two joined 115-minute networks, mirror
alternate, int8) into a bundle, dequantised to float32: what models/lmo ships since stop 57
(docs/experiments/stop-57.md). Run from the repository root, with git history:

    .venv/bin/python scripts/lmo_detector_from_2ab33ed.py models/lmo

The bundle is changed through the staged writer (every file re-hashed; an interruption leaves
it as it was); only detector.onnx and the manifest's `detector` entry change."""
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

COMMIT = "2ab33ed"


def main(bundle: str) -> None:
    from tracker.core.bundle import update_manifest
    from tracker.runtime.fusion import drop_members
    from tracker.training.detector_ensemble import dequantise_graph

    def show(path: str) -> bytes:
        return subprocess.run(["git", "show", f"{COMMIT}:{path}"], check=True, capture_output=True).stdout

    with tempfile.TemporaryDirectory() as tmp:
        int8, flt = Path(tmp) / "int8.onnx", Path(tmp) / "float32.onnx"
        int8.write_bytes(show("models/lmo/detector.onnx"))
        old = json.loads(show("models/lmo/manifest.json"))["detector"]
        counts = dequantise_graph(int8, flt)

        def change(m, stage):
            drop_members(m, Path(stage))  # a fused detector's other networks (stop 67) go too
            shutil.copy(flt, Path(stage) / "detector.onnx")
            det = {k: v for k, v in old.items() if k != "int8"}
            det["float32_from_int8"] = {"method": "tracker.training.detector_ensemble.dequantise_graph", **counts,
                                        "int8_was": old["int8"]}
            det["provenance"] = {"bundle_commit": COMMIT,
                                 "note": "the detector of models/lmo before the 480-minute build (two joined "
                                         "115-minute networks, mirror alternate), its int8 graph dequantised to float32",
                                 "decision": "docs/experiments/stop-57.md"}
            m.detector = det
        update_manifest(bundle, change)
    print(f"{bundle}: detector of {COMMIT}, float32 ({counts})")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    main(sys.argv[1] if len(sys.argv) > 1 else "models/lmo")
