"""The user's jobs: ``app.py COMMAND`` (``app.py --help`` lists them). Each command's parser and
run function live in its own module; this list registers them, in the order ``--help`` shows."""
from __future__ import annotations

from tracker.cli import build, camera, live, scoring, synth, train

COMMANDS = (live.add_demo, live.add_track, live.add_bench, camera.add_calibrate, camera.add_imu, scoring.add_eval,
            scoring.add_score, synth.add_synth, train.add_train, train.add_train_detector, build.add_build,
            scoring.add_report)


def add_commands(sub, REPO) -> None:
    """The user's jobs, each a sub-parser of ``sub``."""
    for add in COMMANDS:
        add(sub, REPO)
