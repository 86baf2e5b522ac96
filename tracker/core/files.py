"""Files written whole or not at all; names OpenCV can open."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

from tracker.core.errors import UserError


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


def not_utf8(name) -> bool:
    """Whether a path or name holds bytes that are not UTF-8 (Python keeps them as lone
    surrogates). OpenCV's readers and writers crash the process on such a name (a segfault, no
    message; opencv-python 5.0), so it is refused before any OpenCV call."""
    try:
        str(name).encode("utf-8")
        return False
    except UnicodeEncodeError:
        return True


def require_utf8(path, what: str = "") -> Path:
    """``path``, or a one-line error naming it when its name is not UTF-8 (:func:`not_utf8`)."""
    if not_utf8(path):
        shown = str(path).encode("utf-8", "backslashreplace").decode("ascii", "backslashreplace")
        raise UserError(f"{what + ' ' if what else ''}{shown}: the name is not UTF-8, which OpenCV cannot open; "
                        f"rename it (e.g. convmv -f latin1 -t utf8)")
    return Path(path)
