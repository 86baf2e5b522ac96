"""Helpers that several commands share (their own and the lab's)."""
from __future__ import annotations

import time
from pathlib import Path


def default_run_dir(name: str) -> Path:
    from tracker.core.paths import REPO
    return REPO / "runs" / f"{name}-{time.strftime('%Y%m%d-%H%M%S')}"


def print_validation(out, manifest) -> None:
    v = manifest.validation_synthetic
    print(f"wrote {out}: synthetic validation median RE {v['regression']['re_median_deg']:.1f} deg "
          f"(AAE {v['aae']['re_median_deg']:.1f}), median TE {v['regression']['te_median_mm']:.1f} mm "
          f"(AAE {v['aae']['te_median_mm']:.1f})")


def para(text: str) -> str:
    import textwrap
    return textwrap.fill(text, 88)
