"""Render assets from Debian packages (issues 57 item 5, 58 item 1): optional folders for
`synth --backgrounds` and `synth --occluders`, never needed by the renderer.

    .venv/bin/python scripts/debian_assets.py textures  --out DIR [--deb FILE]
    .venv/bin/python scripts/debian_assets.py furniture --out DIR [--deb FILE] [--max-cm 80]

`apt-get download`s the pinned package version into a temporary folder (or takes a .deb
fetched before), checks its SHA-256, reads it with the standard library (no dpkg) and writes

    textures:  the surface textures of `openarena-081-textures` as JPEGs (table tops, walls,
               floors; effects, skies and see-through decals left out), GPL-2 like the game
    furniture: the small pieces of `sweethome3d-furniture` (largest side <= --max-cm) as PLY
               meshes in millimetres, z up, textures sampled into vertex colours; CC0 and
               CC-BY-3.0 (the package's copyright file, copied beside them, names the authors)

Both are for training renders only: nothing of them goes into a bundle.
"""
from __future__ import annotations

import argparse
import hashlib
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tracker.core.errors import UserError  # noqa: E402
from tracker.training.synth.assets import deb_files, furniture_from_sh3f, textures_from_pk3  # noqa: E402

PACKAGES = {
    "textures": ("openarena-081-textures", "0.8.5split-14",
                 "72bf05abd5286a1523b56ca04e25bceb775813d747f92ecd20749d512361a81f"),
    "furniture": ("sweethome3d-furniture", "1.8-1",
                  "3ccb90c63f9525e887a767b9cd5c8b6933b8b6b2973a615a5359ee68a2118668"),
}


def fetch(kind: str, deb: str | None, tmp: Path) -> bytes:
    name, version, sha = PACKAGES[kind]
    if deb is None:
        subprocess.run(["apt-get", "download", f"{name}={version}"], cwd=tmp, check=True,
                       stdout=subprocess.DEVNULL)
        deb = str(next(tmp.glob(f"{name}_*.deb")))
    data = Path(deb).read_bytes()
    got = hashlib.sha256(data).hexdigest()
    if got != sha:
        raise UserError(f"{deb}: SHA-256 {got}, expected {sha} ({name} {version}): not the pinned package")
    return data


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("kind", choices=sorted(PACKAGES))
    ap.add_argument("--out", required=True)
    ap.add_argument("--deb", help="the pinned .deb, fetched before (default: apt-get download)")
    ap.add_argument("--max-cm", type=float, default=80.0, help="furniture: largest side at most this")
    a = ap.parse_args(argv)
    out = Path(a.out)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            data = fetch(a.kind, a.deb, Path(tmp))
            if a.kind == "textures":
                (pk3,) = deb_files(data, ".pk3").values()
                written = textures_from_pk3(pk3, out)
            else:
                written = []
                for path, sh3f in sorted(deb_files(data, ".sh3f").items()):
                    written += furniture_from_sh3f(sh3f, out, max_cm=a.max_cm, prefix=Path(path).stem + "_")
                copyright_ = deb_files(data, "/copyright")
                (out / "COPYRIGHT").write_bytes(next(iter(copyright_.values())))
    except (UserError, subprocess.CalledProcessError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"wrote {len(written)} file{'s' if len(written) != 1 else ''} to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
