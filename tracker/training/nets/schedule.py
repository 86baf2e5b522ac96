"""The step size of a network trained to a time budget: a cosine over the budget's fraction spent."""
from __future__ import annotations

import math

from tracker.core.defaults import LR_SCHEDULES  # noqa: F401  (the autoencoder's choices, train --lr-schedule)

FLOOR = 0.02  # the step size at the end of the budget, as a share of the initial one


def budget_lr(lr: float, frac: float, step: int, warmup: int = 0) -> float:
    """``lr`` annealed by a cosine from 1 to ``FLOOR`` as ``frac`` (the share of the time budget
    spent) goes from 0 to 1, after a linear warm-up over the first ``warmup`` steps."""
    frac = min(max(frac, 0.0), 1.0)
    ramp = min(1.0, (step + 1) / warmup) if warmup > 0 else 1.0
    return lr * (FLOOR + (1.0 - FLOOR) * 0.5 * (1.0 + math.cos(math.pi * frac))) * ramp
