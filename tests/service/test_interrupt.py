"""A job stops on cancel where the library reports no progress (service.worker.interrupt).

On a 3M-Gaussian model the frame snap and the relabelling choice run 10-18 s each without a
progress report, so a cancel that only the progress callback could see waited for them. The
end-to-end test stands in for such a stretch with a pure-Python loop in place of align() (a 3M
model's stage takes minutes here); the worker, its heartbeat and the SQLite store are the real ones.
Only work horses are interrupted so (they exit after the job), and what the stop becomes when a
native call wraps it (numba's dispatcher: SystemError) is still the stop.
"""

from __future__ import annotations

import threading
import time

import pytest

from service.worker.interrupt import Interrupter


class Stop(Exception):
    pass


def _busy(seconds: float) -> int:
    """Python work with no report in it, for `seconds`."""
    n, end = 0, time.monotonic() + seconds
    while time.monotonic() < end:
        n += sum(range(200))
    return n


def test_a_stop_reaches_a_thread_that_reports_nothing():
    stopper = Interrupter()
    threading.Timer(0.3, stopper.interrupt, args=(Stop,)).start()
    t = time.monotonic()
    with pytest.raises(Stop), stopper.interruptible():
        _busy(20.0)
    assert time.monotonic() - t < 10.0  # far sooner than the 20 s it would run (about 0.3 s)


def test_a_stop_waits_for_a_shielded_section_and_is_raised_after_it():
    stopper = Interrupter()
    done = []
    with pytest.raises(Stop), stopper.interruptible():
        with stopper.shielded():
            stopper.interrupt(Stop)  # as the heartbeat would, while the callback talks to the store
            _busy(0.3)
            done.append("the shielded section ran to its end")
        _busy(20.0)
    assert done == ["the shielded section ran to its end"]


def test_no_stop_is_raised_outside_the_interruptible_section():
    stopper = Interrupter()
    stopper.interrupt(Stop)  # before the computation: it is refused at the start
    with pytest.raises(Stop), stopper.interruptible():
        pytest.fail("the computation must not start")
    # a stop asked for after the section ended is never raised
    later = Interrupter()
    with later.interruptible():
        _busy(0.05)
    later.interrupt(Stop)
    assert _busy(0.3) > 0


def _submit(settings, backend, pair) -> str:
    from fastapi.testclient import TestClient

    from service.api.app import create_app

    with TestClient(create_app(settings, backend, run_workers=False)) as c:
        with open(pair["source"], "rb") as a, open(pair["target"], "rb") as b:
            r = c.post(
                "/v1/jobs",
                headers={"Authorization": "Bearer k"},
                files=[("source", ("s.ply", a)), ("target", ("t.ply", b))],
                data={"options": '{"stages": ["coarse"], "outputs": ["result"]}'},
            )
    assert r.status_code == 202, r.text
    return r.json()["id"]


def test_cancel_stops_a_job_in_a_stretch_without_progress_reports(tmp_path, pair, monkeypatch):
    import gsa.align.pipeline as pipeline
    from service.backend import make_backend
    from service.models import JobState
    from service.settings import Settings
    from service.worker.execution import execute

    s = Settings(storage_root=tmp_path / "data", api_keys={"k": "me"}, max_attempts=1)
    backend = make_backend(s)
    jid = _submit(s, backend, pair)
    asked = {}

    def silent_align(source, target, opts, progress=None):
        progress("hypotheses", 0.0)
        asked["at"] = time.monotonic()
        backend.store.update(jid, cancel_requested=True)  # what :cancel records
        _busy(30.0)  # no report for 30 s
        raise AssertionError("the stretch ran to its end: the cancel never reached it")

    monkeypatch.setattr(pipeline, "align", silent_align)
    assert execute(jid, backend, interrupt=True) == JobState.cancelled  # as a work horse runs it
    waited = time.monotonic() - asked["at"]
    assert waited < 10.0, f"the cancel took {waited:.1f} s"  # of 30 s; about 0.5 s (CANCEL_POLL_S)
    job = backend.store.get(jid)
    assert job.state == JobState.cancelled and job.result is None


def test_a_stop_wrapped_by_a_native_call_still_ends_the_job_as_the_stop(tmp_path, pair, monkeypatch):
    """The fine stage's renderer: the stop raised in numba's dispatcher surfaces as SystemError."""
    import gsa.align.pipeline as pipeline
    from service.backend import make_backend
    from service.models import JobState
    from service.settings import Settings
    from service.worker.execution import execute

    s = Settings(storage_root=tmp_path / "data", api_keys={"k": "me"}, max_attempts=1)
    backend = make_backend(s)
    jid = _submit(s, backend, pair)

    def wrapping_align(source, target, opts, progress=None):
        progress("fine", 0.0)
        backend.store.update(jid, cancel_requested=True)
        try:
            _busy(30.0)
        except Exception as exc:
            raise SystemError("CPUDispatcher(<function _forward>) returned a result with an exception set") from exc
        raise AssertionError("the stretch ran to its end: the cancel never reached it")

    monkeypatch.setattr(pipeline, "align", wrapping_align)
    assert execute(jid, backend, interrupt=True) == JobState.cancelled
    assert backend.store.get(jid).error is None
