"""What ends a reconstruction early, turned into a result rather than lost work.

`RunPhases` wraps one run. SIGINT and SIGTERM (main thread only; elsewhere SIGINT's usual
KeyboardInterrupt is caught the same way) and the time budget end it according to its phase:

- ``read`` (bundle and problem): a signal is held until the problem is built, since without
  the problem there is nothing to write;
- ``setup`` (the method's set-up): a signal raises `Interrupted` at once, the run's clock
  (rngcam.recon.loop.Clock) past its deadline raises
  `BudgetCut` at once (a timer, so even a long set-up stage is cut), and the runner writes
  the start video as the result;
- ``solve``: a signal asks the loop to stop after the current step (`stop_reason`); a second
  one raises `Interrupted` in the step, and the loop rolls back to its last good state;
- ``finish`` (metrics and outputs): signals are held so the outputs are written whole.
"""

from __future__ import annotations

import signal
import threading

from rngcam.recon.loop import Clock


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM (or a notebook's interrupt) ended the run; `signame` says which."""

    def __init__(self, signame: str = "SIGINT"):
        super().__init__(signame)
        self.signame = signame


class BudgetCut(BaseException):
    """The time budget ran out before the method's set-up finished (a BaseException so that no
    method's `except Exception` swallows it)."""


class RunPhases:
    """Signal handlers, the run's phase, and its clock (set-up is cut at its deadline); a context manager."""

    def __init__(self, clock: Clock):
        self.phase = "read"
        self.signame: str | None = None  # the first signal received
        self.clock = clock
        self._old: dict = {}
        self._main = threading.current_thread() is threading.main_thread()

    def __enter__(self) -> RunPhases:
        if self._main:
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._on_signal)
            if hasattr(signal, "SIGALRM"):
                self._old[signal.SIGALRM] = signal.signal(signal.SIGALRM, self._on_alarm)
        return self

    def __exit__(self, *exc) -> bool:
        self._disarm()
        for sig, old in self._old.items():
            signal.signal(sig, old)
        return False

    # ------------------------------------------------------------------ phases

    def enter(self, phase: str) -> None:
        """Move to `phase`; a signal held in `read` is raised on entering `setup`."""
        self.phase = phase
        if phase == "setup":
            self._arm()
            self.check()
        else:
            self._disarm()

    def check(self) -> None:
        """Raise what is due now in set-up (called at every stage line, so a run in a thread without
        signal handlers is cut too); nothing in the other phases."""
        if self.signame is not None and self.phase == "setup":
            raise Interrupted(self.signame)
        if self.phase == "setup" and self.clock.expired():
            raise BudgetCut()

    def stop_reason(self) -> str | None:
        """For the loop: why it should stop after this step (a signal), or None."""
        return None if self.signame is None else f"interrupted by {self.signame}"

    # ------------------------------------------------------------------ handlers

    def _on_signal(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        first = self.signame is None
        self.signame = self.signame or name
        if self.phase == "setup" or (self.phase == "solve" and not first):
            raise Interrupted(name)

    def _on_alarm(self, signum, frame) -> None:
        if self.phase == "setup":
            raise BudgetCut()

    def _arm(self) -> None:
        left = self.clock.left()
        if not (self._main and hasattr(signal, "setitimer")) or left is None:
            return
        signal.setitimer(signal.ITIMER_REAL, max(left, 1e-3))

    def _disarm(self) -> None:
        if self._main and hasattr(signal, "setitimer"):
            signal.setitimer(signal.ITIMER_REAL, 0)
