"""What this CPU computes natively, from Linux's /proc/cpuinfo flags (empty elsewhere)."""
from __future__ import annotations

from pathlib import Path


def cpu_flags(cpuinfo: str | None = None) -> set[str]:
    """The instruction-set flags the CPU advertises (``cpuinfo``: the file's text, for tests)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return set()
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            flags.update(line.split(":", 1)[-1].split())
    return flags


def int8_vnni(cpuinfo: str | None = None) -> bool:
    """True when the CPU has 8-bit dot products (VNNI or AMX). Without them onnxruntime runs
    uint8 x int8 convolutions on AVX2, where its docs warn that the sums can saturate: the
    shipped int8 detector scores lower there (tests/test_shipped_bundle.py)."""
    return bool(cpu_flags(cpuinfo) & {"avx512_vnni", "avx_vnni", "amx_int8"})
