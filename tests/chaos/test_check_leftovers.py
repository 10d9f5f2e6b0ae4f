"""Characterisation of ``bench.bench_chaos.Session.check_leftovers`` (issue 31): what it
says and removes, before its split, for /dev/shm as a trial leaves it: the buffer and the
world model (by design), a stale file of the session's name, files the processes mapped
that are still there (zenoh's own: a note; another: a failure), and a clean session."""

from __future__ import annotations

import os
import uuid
from types import SimpleNamespace

import pytest

from bench.bench_chaos import Outcome, Session, Trial


def _touch(path: str) -> str:
    with open(path, "wb") as f:
        f.write(b"\0" * 16)
    return path


@pytest.fixture
def sess(tmp_path):
    s = Session("controller", tmp_path)
    made: list[str] = []
    yield s, made
    for f in made:
        if os.path.exists(f):
            os.unlink(f)


def _out() -> Outcome:
    return Outcome(Trial("controller", 0, "running", "SIGKILL", 0.5, 0.1))


def test_leftovers_fail_naming_each_file_and_note_zenohs_own(sess):
    s, made = sess
    tag = uuid.uuid4().hex[:6]
    buf, wm = _touch(f"/dev/shm/{s.name}"), _touch(f"/dev/shm/{s.wm}")
    stale = _touch(f"/dev/shm/{s.name}.ring")
    other = _touch(f"/dev/shm/pfma-cc-test-{tag}")
    zen = _touch(f"/dev/shm/pfma-cc-test-{tag}.zenoh")
    made += [buf, wm, stale, other, zen]
    s.procs = [SimpleNamespace(role="controller", maps={other, zen, f"/dev/shm/{s.name}"}),
               SimpleNamespace(role="recorder", maps={other, "/dev/shm/pfma-cc-gone"})]
    out = _out()
    s.check_leftovers(out)
    assert out.checks == {"no_leftovers": (
        False, f"left in /dev/shm: {s.name}.ring, {other} (mapped by the controller, the recorder)")}
    assert out.notes == [f"zenoh shared-memory files still there after its processes stopped: {zen} "
                         f"(zenoh removes them when a zenoh session next starts)"]
    assert out.figures == {"zenoh_files_left": 1}
    assert not os.path.exists(stale) and not os.path.exists(buf) and not os.path.exists(wm)
    assert os.path.exists(other) and os.path.exists(zen)  # not ours: named, not removed


def test_a_clean_session_has_no_leftovers(sess):
    s, made = sess
    made += [_touch(f"/dev/shm/{s.name}"), _touch(f"/dev/shm/{s.wm}")]
    s.procs = [SimpleNamespace(role="service", maps={f"/dev/shm/{s.name}"})]
    out = _out()
    s.check_leftovers(out)
    assert out.checks == {"no_leftovers": (True, "none")}
    assert out.notes == [] and out.figures == {}
    assert not os.path.exists(f"/dev/shm/{s.name}") and not os.path.exists(f"/dev/shm/{s.wm}")


def test_without_an_outcome_it_only_cleans(sess):
    s, made = sess
    stale = _touch(f"/dev/shm/{s.name}.x")
    made.append(stale)
    s.procs = []
    s.check_leftovers(None)
    assert not os.path.exists(stale)
