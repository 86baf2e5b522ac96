#!/usr/bin/env python3
"""autopose command line: ``python app.py --help``. With no arguments, runs the demo."""
import sys

from tracker.cli import main

if __name__ == "__main__":
    sys.exit(main())
