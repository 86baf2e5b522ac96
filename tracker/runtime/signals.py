"""Ctrl-C and SIGTERM in a run: the loop ends after the frame in flight (:class:`Stopper`); while
the run's files are finished, the first signal is noted and the work goes on
(:class:`Deferred`); in a long job (synth, training, build) SIGTERM is Ctrl-C
(:func:`sigterm_as_ctrl_c`)."""
from __future__ import annotations

import signal


class Stopper:
    """SIGINT / SIGTERM end the loop after the frame in flight."""

    def __init__(self):
        self.stop = False
        self._old = {}

    def __enter__(self):
        for s in (signal.SIGINT, signal.SIGTERM):
            self._old[s] = signal.signal(s, self._handle)
        return self

    def _handle(self, *_):
        self.stop = True

    def __exit__(self, *exc):
        for s, h in self._old.items():
            signal.signal(s, h)


class Deferred(Stopper):
    """SIGINT / SIGTERM while the run's files are being finished: the first is noted (and
    said) and the work goes on; a second one stops it (KeyboardInterrupt)."""

    def __init__(self, log, what: str):
        super().__init__()
        self.log, self.what = log, what

    @property
    def hit(self) -> bool:
        return self.stop

    def _handle(self, *_):
        if self.stop:
            raise KeyboardInterrupt
        self.stop = True
        self.log(f"{self.what}; interrupt again to skip it")


def sigterm_as_ctrl_c() -> None:
    """SIGTERM (a cluster scheduler's stop, ``kill``) ends a long job as Ctrl-C does: the
    detector's checkpoint is written, a build keeps its finished stages and the time spent."""
    def stop(signum, frame):
        raise KeyboardInterrupt
    signal.signal(signal.SIGTERM, stop)
