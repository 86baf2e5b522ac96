#!/usr/bin/env python3
"""autopose command line: ``python app.py --help``. With no arguments, runs the demo."""
import os
import sys

if not os.environ.get("AUTOPOSE_DEBUG"):  # set before OpenCV loads: its and FFmpeg's own log lines
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")  # would come before our one-line errors
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

# torch's CPU allocator: blocks of 2 MB and more on transparent huge pages (read before torch
# allocates). Training on this CPU otherwise spent a quarter of its time in page faults (343,000
# a second) whenever glibc handed its batch-sized buffers back to the kernel after each step.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

from tracker.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
