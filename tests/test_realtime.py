"""Real-time scheduling of the control loop's thread (companion/service/realtime.py, control.realtime_priority):
the function on its own thread, its refusal, and the daemon as a real process, whose loop thread
alone is SCHED_FIFO while its mapper, executor and Zenoh threads stay at normal scheduling."""

from __future__ import annotations

import concurrent.futures
import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from companion.config import ConfigError, load_config
from companion.service import realtime
from tests.processes import companion, free_port, stop, write_config

pytestmark = pytest.mark.skipif(not realtime.supported(), reason="thread scheduling policies are Linux's")

FIFO_ALLOWED = subprocess.run(
    [sys.executable, "-c", "import os; os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))"],
    capture_output=True, timeout=30).returncode == 0


def policy_of(tid: int) -> int:
    return os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK


def on_new_thread(fn):
    """Run ``fn()`` on a fresh thread (so the test's own thread keeps its scheduling) -> its result."""
    out = {}

    def body():
        try:
            out["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - re-raised in the test's thread
            out["error"] = exc

    t = threading.Thread(target=body)
    t.start()
    t.join(30)
    if "error" in out:
        raise out["error"]
    return out["value"]


def test_enter_fifo_changes_only_the_calling_thread_and_restore_undoes_it():
    main_before = realtime.current()

    def body():
        before, reason = realtime.enter_fifo(10)
        inside = realtime.current()
        with concurrent.futures.ThreadPoolExecutor(1, initializer=realtime.normal_scheduling) as pool:
            worker = pool.submit(realtime.current).result(10)
        plain = []  # a thread started by it (SCHED_RESET_ON_FORK: normal, whatever the initializer)
        t = threading.Thread(target=lambda: plain.append(realtime.current()))
        t.start()
        t.join(10)
        realtime.restore(before)
        return before, reason, inside, worker, plain[0], realtime.current()

    before, reason, inside, worker, plain, after = on_new_thread(body)
    normal = realtime.Scheduling(os.SCHED_OTHER, 0)
    assert realtime.current() == main_before  # the test's thread is untouched either way
    if FIFO_ALLOWED:
        assert reason == "" and before == normal
        assert inside == realtime.Scheduling(os.SCHED_FIFO, 10)
        assert plain == normal, "SCHED_RESET_ON_FORK: threads it starts begin at normal scheduling"
        assert worker == normal
        assert after == normal
    else:
        assert before is None and "refused" in reason
        assert inside == plain == worker == after == normal


def test_io_threads_go_one_priority_below_the_loop():
    def body():
        before, reason = realtime.enter_fifo(10)
        with concurrent.futures.ThreadPoolExecutor(1, initializer=realtime.below, initargs=(10,)) as pool:
            io = pool.submit(realtime.current).result(10)
        with concurrent.futures.ThreadPoolExecutor(1, initializer=realtime.below, initargs=(1,)) as pool:
            lowest = pool.submit(realtime.current).result(10)
        realtime.restore(before)
        return reason, io, lowest

    reason, io, lowest = on_new_thread(body)
    if FIFO_ALLOWED:
        assert reason == ""
        assert io == realtime.Scheduling(os.SCHED_FIFO, 9)
        assert lowest == realtime.Scheduling(os.SCHED_FIFO, 1)
    else:
        assert io == lowest == realtime.Scheduling(os.SCHED_OTHER, 0)


def test_yield_to_others_lowers_only_the_calling_thread():
    """The dense flow's thread lowers itself (mapper.flow_thread_nice): its own nice value changes,
    never back up, and the thread that started it keeps its own."""
    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    if mine >= 19:
        pytest.skip("the test runs at nice 19 already: there is no lower priority to take")
    target = min(19, mine + 7)

    def body():
        got, why = realtime.yield_to_others(target)
        again = realtime.yield_to_others(0)  # never back up: a thread already nicer keeps its own
        return got, why, again, os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    got, why, again, theirs = on_new_thread(body)
    assert why == "" and got == theirs == target and again == (target, "")
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == mine


def test_a_refusal_leaves_the_thread_as_it_was_and_says_how_to_allow_it(monkeypatch):
    def refuse(*_):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    before, reason = on_new_thread(lambda: realtime.enter_fifo(10))
    assert before is None
    assert "LimitRTPRIO=10" in reason and "CAP_SYS_NICE" in reason


@pytest.mark.parametrize("priority", [0, 100, -1])
def test_enter_fifo_refuses_a_priority_outside_1_to_99(priority):
    with pytest.raises(ValueError, match="1-99"):
        realtime.enter_fifo(priority)


def test_the_configuration_bounds_the_priority(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("control:\n  realtime_priority: 120\n")
    with pytest.raises(ConfigError, match="control.realtime_priority"):
        load_config(path)
    path.write_text("control:\n  realtime_priority: 10\n")
    assert load_config(path).control.realtime_priority == 10


def receive_until(sock: socket.socket, wanted: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if wanted in sock.recv(4096).decode().split("\n"):
                return
        except TimeoutError:
            continue
    raise TimeoutError(f"no {wanted} within {timeout_s} s")


@pytest.mark.slow
def test_the_daemon_runs_its_loop_thread_alone_at_sched_fifo(tmp_path):
    """``companion run`` with control.realtime_priority 10: after READY and a few snapshots, the loop's
    thread (the main thread) is SCHED_FIFO 10, the I/O executor's threads SCHED_FIFO 9, and the mapper,
    snapshot and Zenoh threads normal; where the system refuses, every thread is normal and the log
    says why. SIGTERM still ends it cleanly."""
    cfg = write_config(tmp_path / "c.yaml", {
        "link": {"connection": f"udpin:127.0.0.1:{free_port(socket.SOCK_DGRAM)}", "heartbeat_timeout_s": 1.5},
        "camera": {"source": "synthetic", "rate_hz": 15.0},
        "zenoh": {"enabled": True, "mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
        "persistence": {"directory": str(tmp_path / "map"), "snapshot_interval_s": 0.5},
        "control": {"realtime_priority": 10},
    })
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(tmp_path / "notify.sock"))
    sock.settimeout(0.5)
    log = tmp_path / "daemon.log"
    proc = companion("run", "--config", str(cfg), env={"NOTIFY_SOCKET": str(tmp_path / "notify.sock")}, log=log)
    try:
        receive_until(sock, "READY=1", 30)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not list((tmp_path / "map").glob("*snapshot*")):
            time.sleep(0.2)
        time.sleep(1.5)  # more snapshots: executor threads at work
        policies = {}
        for tid in map(int, os.listdir(f"/proc/{proc.pid}/task")):
            try:
                policies[tid] = (policy_of(tid), os.sched_getparam(tid).sched_priority)
            except ProcessLookupError:
                pass  # a thread that ended meanwhile
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(10)
    finally:
        stop(proc)
        sock.close()
    text = log.read_text()
    assert rc == 0, text[-2000:]
    assert list((tmp_path / "map").glob("*snapshot*")), "no snapshot written: the executor threads never ran"
    others = [p for tid, p in policies.items() if tid != proc.pid]
    print(f"{len(policies)} threads; main {policies.get(proc.pid)}; others {sorted(others)}")
    normal, io = (os.SCHED_OTHER, 0), (os.SCHED_FIFO, 9)
    # normal: the mapper thread, the snapshot thread, Zenoh's threads
    assert others.count(normal) >= 3
    if FIFO_ALLOWED:
        assert policies[proc.pid] == (os.SCHED_FIFO, 10)
        assert "SCHED_FIFO priority 10" in text
        assert io in others  # the executor's (the camera's start-up ran there)
        assert set(others) <= {normal, io}
    else:
        assert policies[proc.pid] == normal and set(others) == {normal}
        assert "control loop at normal priority" in text and "LimitRTPRIO=10" in text
