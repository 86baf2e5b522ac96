"""Files written whole or not at all."""
from __future__ import annotations

from pathlib import Path
from typing import Callable


def write_whole(path, write: Callable[[Path], None]) -> Path:
    """``write(tmp)`` writes the file beside ``path`` (same suffix), which then replaces ``path``
    in one step: Ctrl-C, a kill or a full disk midway leave the previous file (or none), never a
    part-written one that the next run fails to read (a checkpoint, a cache of crops)."""
    path = Path(path)
    tmp = path.with_name(f"{path.stem}.part{path.suffix}")
    try:
        write(tmp)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
