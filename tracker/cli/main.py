"""Command line: a thin layer over the library. ``python app.py --help`` lists the user's jobs,
``python app.py lab --help`` the research tools."""
from __future__ import annotations

import argparse
import os
import sys
import warnings

from tracker.core.errors import UserError


def build_parser() -> argparse.ArgumentParser:
    from tracker import __version__
    from tracker.cli import jobs, lab
    from tracker.core.paths import REPO
    p = argparse.ArgumentParser(prog="app.py", description="autopose: real-time monocular 6-DoF "
                                "pose tracking from an autoencoder latent (Auto-Pose).",
                                epilog="research tools (joins, refits, tuning, ablations, data helpers): app.py lab --help")
    p.add_argument("--version", action="version", version=f"autopose {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    jobs.add_commands(sub, REPO)
    s = sub.add_parser("lab", help="research tools: joins, refits and tuning of bundles, ablations, data helpers")
    labsub = s.add_subparsers(dest="lab_command", metavar="LAB_COMMAND")
    s.set_defaults(func=lambda args: _lab_help(s))
    lab.add_commands(labsub, REPO)
    return p


def _lab_help(parser) -> int:
    parser.print_help()
    return 2


def _process_env() -> None:
    """Settings read when a library loads, so set before the commands import it (as app.py does, for
    the console script ``autopose`` too)."""
    if not os.environ.get("AUTOPOSE_DEBUG"):  # before OpenCV loads: its and FFmpeg's own log lines
        os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")  # would come before our one-line errors
        os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    # torch's CPU allocator: blocks of 2 MB and more on transparent huge pages (read before torch allocates)
    os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")


def _check_names(args) -> None:
    """Every path or name given is UTF-8: OpenCV crashes the process on any other (tracker.core.files)."""
    from tracker.core.files import require_utf8
    for key, value in vars(args).items():
        for v in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(v, str):
                require_utf8(v, f"--{key.replace('_', '-')}")


def main(argv=None) -> int:
    """``python app.py`` and the console script ``autopose``: the exit status."""
    _process_env()
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    if not argv:
        argv = ["demo"]
    args = parser.parse_args(argv)
    warnings.simplefilter("default")
    warnings.formatwarning = lambda msg, cat, *a, **k: f"warning: {msg}\n"
    try:
        _check_names(args)
        return args.func(args)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except OSError as e:  # a path that is missing, a folder, a file where a folder should be, not writable
        where = f": {e.filename}" if getattr(e, "filename", None) else ""
        print(f"error: {e.strerror or e}{where}", file=sys.stderr)
        return 1
    except Exception as e:  # a bug, not bad input: one line unless asked for more
        if os.environ.get("AUTOPOSE_DEBUG"):
            raise
        print(f"internal error: {e.__class__.__name__}: {e} (rerun with AUTOPOSE_DEBUG=1 for the traceback)",
              file=sys.stderr)
        return 3
