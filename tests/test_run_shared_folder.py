"""conftest.run_shared_folder: a fixture's folder made once per test run, shared by the
pytest-xdist workers (each with its own session) through a lock and a rename."""
from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from conftest import run_shared_folder


class Base:
    """Stands in for pytest's tmp_path_factory: only getbasetemp() is used."""

    def __init__(self, path: Path):
        self.path = path

    def getbasetemp(self) -> Path:
        return self.path


def test_made_once_per_inputs_and_complete_when_it_exists(tmp_path, monkeypatch):
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)
    calls = []

    def make(d: Path):
        calls.append(d)
        (d / "data.txt").write_text("x")

    a = run_shared_folder(Base(tmp_path), "caps", {"seed": 1}, make)
    b = run_shared_folder(Base(tmp_path), "caps", {"seed": 1}, make)
    assert a == b and len(calls) == 1 and (a / "data.txt").read_text() == "x"
    c = run_shared_folder(Base(tmp_path), "caps", {"seed": 2}, make)         # other inputs: another folder
    assert c != a and len(calls) == 2
    assert not list(tmp_path.glob("*.part"))                                  # made under a temporary name


def test_a_worker_uses_the_base_its_siblings_share(tmp_path, monkeypatch):
    """Under xdist each worker's base temp is a sub-folder of the run's; the folder goes there."""
    monkeypatch.setenv("PYTEST_XDIST_WORKER", "gw1")
    worker = tmp_path / "popen-gw1"
    worker.mkdir()
    d = run_shared_folder(Base(worker), "caps", [1], lambda p: None)
    assert d.parent == tmp_path


def test_a_failed_make_leaves_nothing_and_the_next_caller_tries_again(tmp_path, monkeypatch):
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)

    def broken(d: Path):
        (d / "half.txt").write_text("half")
        raise RuntimeError("render failed")

    with pytest.raises(RuntimeError, match="render failed"):
        run_shared_folder(Base(tmp_path), "caps", 1, broken)
    assert [p.name for p in tmp_path.iterdir() if not p.name.endswith(".lock")] == []
    d = run_shared_folder(Base(tmp_path), "caps", 1, lambda p: (p / "ok.txt").write_text("ok"))
    assert (d / "ok.txt").is_file() and not (d / "half.txt").exists()


def test_concurrent_callers_wait_for_one_make(tmp_path, monkeypatch):
    """Two callers at once (separate lock-file descriptions, as two worker processes have):
    one makes the folder, the other waits for the lock and gets the finished folder."""
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)
    calls, results = [], []

    def slow(d: Path):
        calls.append(d)
        time.sleep(0.5)
        (d / "done.txt").write_text("done")

    def caller():
        d = run_shared_folder(Base(tmp_path), "caps", "k", slow, poll_s=0.01)
        results.append((d / "done.txt").read_text())

    threads = [threading.Thread(target=caller) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert len(calls) == 1 and results == ["done", "done"]


def test_a_lock_held_too_long_is_a_named_timeout(tmp_path, monkeypatch):
    import fcntl

    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)
    run_shared_folder(Base(tmp_path), "caps", "k", lambda p: None)        # learn the lock's name
    (lock,) = tmp_path.glob(".shared-caps-*.lock")
    with open(lock, "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        with pytest.raises(TimeoutError, match=str(lock)):
            run_shared_folder(Base(tmp_path), "caps", "k", lambda p: None, wait_s=0.2, poll_s=0.05)
