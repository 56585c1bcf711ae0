"""The one progress protocol (core/base/progress.py): the sub-range mapper and the cancel check."""

from __future__ import annotations

import multiprocessing
import threading

import numpy as np
import pytest

from shapegen_core.base.errors import Cancelled
from shapegen_core.base.progress import CancelCheck, no_progress, sub_range


def test_sub_range_maps_a_steps_fraction_into_the_callers_range():
    seen = []
    step = sub_range(lambda f, m: seen.append((f, m)), 0.15, 0.75, "correspondence: ")
    for fraction in (0.0, 0.5, 1.0):
        step(fraction, "registering vase_001")
    assert [f for f, _ in seen] == [0.15, pytest.approx(0.45), 0.75]
    assert {m for _, m in seen} == {"correspondence: registering vase_001"}
    seen.clear()
    step(-0.5, "below")
    step(1.5, "above")  # a step never reports outside its range
    assert [f for f, _ in seen] == [0.15, 0.75]
    assert sub_range(None, 0.2, 0.4) is no_progress


def test_nested_sub_ranges_stay_monotone_and_end_exactly_at_one():
    seen = []
    outer = sub_range(lambda f, m: seen.append(f), 0.15, 0.75)
    rounds = 3
    for r in range(rounds):
        step = sub_range(outer, r / rounds, (r + 1) / rounds)
        for fraction in np.linspace(0.0, 1.0, 101):
            step(float(fraction), "")
    assert seen == sorted(seen) and seen[0] == 0.15 and seen[-1] == 0.75
    whole = []
    last = sub_range(sub_range(lambda f, m: whole.append(f), 0.75, 1.0), 2 / 3, 1.0)
    last(1.0, "")
    assert whole == [1.0]


@pytest.mark.parametrize("kind", ["none", "callable", "thread event", "process event"])
def test_cancel_check_accepts_none_a_callable_or_an_event(kind):
    if kind == "none":
        check = CancelCheck(None, "fit")
        assert not check.is_set()
        check()  # never raises
        return
    if kind == "callable":
        flag = {"stop": False}
        should_cancel, stop = (lambda: flag["stop"]), (lambda: flag.update(stop=True))
    else:
        event = threading.Event() if kind == "thread event" else multiprocessing.get_context("spawn").Event()
        should_cancel, stop = event, event.set
    check = CancelCheck(should_cancel, "correspondence")
    check()
    assert not check.is_set()
    stop()
    assert check.is_set()
    with pytest.raises(Cancelled, match="^correspondence cancelled$"):
        check()
    # itself Event-like: passed on as another step's should_cancel, that step names itself
    with pytest.raises(Cancelled, match="^prepare cancelled$"):
        CancelCheck(check, "prepare")()


def test_cancel_check_before_progress_stops_at_the_next_report():
    stop = threading.Event()
    seen = []
    report = CancelCheck(stop, "prepare").before(lambda f, m: seen.append(m))
    report(0.1, "principal axes")
    stop.set()
    with pytest.raises(Cancelled, match="prepare cancelled"):
        report(0.2, "landmarks")
    assert seen == ["principal axes"]
    CancelCheck(None, "prepare").before(None)(0.5, "no progress wanted")  # both optional


def test_cancel_check_refuses_anything_else():
    with pytest.raises(TypeError, match="should_cancel"):
        CancelCheck(True, "fit")
