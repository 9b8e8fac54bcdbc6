"""gsa.render.steps.parallel: independent calls side by side, the calling thread still
reporting (its callback) while it waits, so a cancelled job stops there."""

from __future__ import annotations

import threading
import time

import pytest

from gsa.render import steps


@pytest.fixture
def two_cores(monkeypatch):
    monkeypatch.setattr(steps, "_cores", lambda: 2)


def test_parallel_runs_the_calls_side_by_side_and_keeps_their_order(two_cores):
    both_running = threading.Barrier(2, timeout=5)  # broken (an error) unless two calls run at once

    def call(value):
        both_running.wait()
        return value, threading.current_thread().name

    values = steps.parallel([lambda: call("a"), lambda: call("b")])
    assert [v for v, _ in values] == ["a", "b"]
    assert all(name.startswith("gsa-steps-parallel") for _, name in values)


def test_parallel_reports_on_the_calling_thread_while_it_waits(two_cores):
    reports = []
    with steps.between_steps(lambda: reports.append(threading.current_thread().name)):
        assert steps.parallel([lambda: time.sleep(0.3) or 1, lambda: 2]) == [1, 2]
    assert len(reports) >= 3
    assert set(reports) == {threading.current_thread().name}


def test_a_report_that_raises_stops_the_wait_and_drops_the_calls_not_started(two_cores):
    release, started = threading.Event(), []

    def call(i):
        started.append(i)
        release.wait(5)
        return i

    def cancel():
        raise RuntimeError("job cancelled")

    t = time.perf_counter()
    with steps.between_steps(cancel), pytest.raises(RuntimeError, match="job cancelled"):
        steps.parallel([lambda i=i: call(i) for i in range(6)])
    assert time.perf_counter() - t < 2
    release.set()
    time.sleep(0.2)
    assert sorted(started) == [0, 1]  # the two running finished unwaited for; the other four never ran


def test_a_call_that_raises_is_raised_to_the_caller(two_cores):
    def fails():
        raise ValueError("bad pose")

    with pytest.raises(ValueError, match="bad pose"):
        steps.parallel([lambda: 1, fails])


def test_one_core_runs_the_calls_here_in_order(monkeypatch):
    monkeypatch.setattr(steps, "_cores", lambda: 1)
    here = threading.current_thread().name
    assert steps.parallel([lambda: (1, threading.current_thread().name), lambda: (2, here)]) == [(1, here), (2, here)]


def test_parallel_map_keeps_the_items_order(two_cores):
    assert steps.parallel_map(lambda x: x * x, range(7)) == [0, 1, 4, 9, 16, 25, 36]
