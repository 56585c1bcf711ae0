"""The one progress protocol and the one cancel check of every long computation.

`progress(fraction, message)`: `fraction` in [0, 1], never decreasing within a job and 1.0
at its end; `message` says what is being done (stage, shape name). A step of a larger job
reports its own 0..1 through `sub_range`, which the caller maps into its share.

`should_cancel`: None, a callable returning True once the caller wants to stop, or an
Event-like object with `is_set()` (threading or multiprocessing). `CancelCheck` accepts
all three and raises `errors.Cancelled` naming what was cancelled.
"""

from __future__ import annotations

from typing import Callable

from .errors import Cancelled

__all__ = ["Progress", "CancelCheck", "no_progress", "sub_range"]

#: progress(fraction in [0, 1], message)
Progress = Callable[[float, str], None]


def no_progress(fraction: float, message: str) -> None:
    """The default progress: reports nothing."""


def sub_range(progress: Progress | None, start: float, end: float, prefix: str = "") -> Progress:
    """A progress for one step of the caller's job: the step's own fraction f in [0, 1]
    is reported as start + (end − start) · f (exactly `end` at f = 1, never beyond it, so
    a monotone step stays monotone), its message after `prefix`."""
    if progress is None:
        return no_progress

    def report(fraction: float, message: str) -> None:
        fraction = min(max(fraction, 0.0), 1.0)
        progress(end if fraction >= 1.0 else min(end, start + (end - start) * fraction), prefix + message)

    return report


def _never() -> bool:
    return False


class CancelCheck:
    """The cancel check of one computation: calling it raises errors.Cancelled
    ("<what> cancelled") once `should_cancel` (None, a callable or an Event-like object
    with is_set()) says so. Itself Event-like, so it can be passed on as `should_cancel`."""

    def __init__(self, should_cancel=None, what: str = "job"):
        if should_cancel is None:
            self._asked = _never
        elif hasattr(should_cancel, "is_set"):
            self._asked = should_cancel.is_set
        elif callable(should_cancel):
            self._asked = should_cancel
        else:
            raise TypeError("should_cancel must be None, a callable or have is_set(), "
                            f"got {type(should_cancel).__name__}")
        self.what = what

    def is_set(self) -> bool:
        """Whether cancel was asked (without raising)."""
        return bool(self._asked())

    def __call__(self) -> None:
        if self.is_set():
            raise Cancelled(f"{self.what} cancelled")

    def before(self, progress: Progress | None) -> Progress:
        """`progress` that checks for cancel first: a step that reports progress stops at
        its next report once cancel was asked."""
        report = progress or no_progress

        def checked(fraction: float, message: str) -> None:
            self()
            report(fraction, message)

        return checked
