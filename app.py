#!/usr/bin/env python3
"""autopose command line: ``python app.py --help``. With no arguments, runs the demo. The same
command line as the console script ``autopose`` (both call :func:`tracker.cli.main`, which sets
the environment OpenCV and torch read before either loads)."""
import sys

from tracker.cli import main

if __name__ == "__main__":
    sys.exit(main())
