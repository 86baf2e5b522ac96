"""Command line: ``python app.py --help``."""
from tracker.cli.main import main

__all__ = ["main"]
