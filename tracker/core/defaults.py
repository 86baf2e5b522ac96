"""Defaults and choices that the command line shows and the training code uses, defined once here,
outside ``tracker.training``: building the parser (``app.py demo`` too) must not import training
code. Plain constants only: no imports, no torch."""
from __future__ import annotations

# synth's and build's default: the objects rendered at about this many faces (stop 47)
SYNTH_FACES = 4000

# the autoencoder's step-size schedules (train --lr-schedule; tracker.training.nets.schedule)
LR_SCHEDULES = ("budget", "plateau")

# the arithmetic of the training passes (--precision; tracker.training.nets.precision)
PRECISIONS = ("auto", "bf16", "fp32")

# the detector's backbones (train-detector --backbone, build --detector-backbone):
# tracker.training.nets.detector.make_detector
DETECTOR_BACKBONES = ("plain", "lite0", "lite1", "lite2", "nanodet")
