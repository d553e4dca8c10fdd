"""Lockstep between the simulator and the service: one clock file, held while frames wait for the
workers (drivers/clock.py SharedClock, companion/service/lockstep.py, docs/sim.md "Lockstep")."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import time

import numpy as np
import pytest

from companion.config import CompanionConfig, ConfigError
from companion.config import replace as replace_config
from companion.method.messages import Frame
from companion.service.daemon import FrameQueue, clock_from_config
from companion.service.lockstep import MAPPER_LEAD_PERIODS, FrameLockstep
from drivers.clock import SharedClock

PERIOD_S = 1.0 / 15.0


def _frame(sequence: int, t_s: float) -> Frame:
    return Frame(t_s=t_s, image=np.zeros((2, 2), np.uint8), sequence=sequence, source="synthetic")


def test_another_process_reads_the_same_time_and_waits_at_the_hold(tmp_path):
    path = tmp_path / "clock"
    clock = SharedClock.create(str(path), speedup=4.0)
    clock.hold_at(clock.now() + 0.2)  # 0.05 s of wall time, then time waits
    reader = ("import sys, time; from drivers.clock import SharedClock; c = SharedClock.open(sys.argv[1]); "
              "a = c.now(); time.sleep(0.3); print(c.speedup, a, c.now(), c.held)")
    out = subprocess.run([sys.executable, "-c", reader, str(path)], capture_output=True, text=True, timeout=60, check=True)
    speedup, before, after, held = out.stdout.split()
    assert float(speedup) == 4.0
    assert float(after) == clock.now()  # both processes held at the same instant
    assert float(before) <= float(after) and held == "True"
    clock.release()
    assert not clock.held
    clock.close()


def test_time_held_then_released_goes_on_from_the_hold(tmp_path):
    clock = SharedClock.create(str(tmp_path / "clock"), speedup=10.0)
    hold = clock.now() + 0.1
    clock.hold_at(hold)
    time.sleep(0.2)  # 2 s of clock time would have passed: held at the hold
    assert clock.now() == hold and clock.held
    clock.hold_at(hold - 1.0)  # a hold in the past holds at now: time does not go back
    assert clock.now() == hold
    clock.release()
    t = clock.now()
    assert hold <= t < hold + 1.0  # no jump to where it would have been (hold + 1.9 s): it goes on from the hold
    clock.close()


def test_a_sleeper_waits_while_held_and_wakes_once_released(tmp_path):
    clock = SharedClock.create(str(tmp_path / "clock"), speedup=20.0)

    async def scenario():
        hold = clock.now() + 0.05
        clock.hold_at(hold)
        sleeper = asyncio.create_task(clock.sleep_until(hold + 0.5))
        await asyncio.sleep(0.2)  # 4 s of clock time unheld; held, it stays at the hold
        assert not sleeper.done() and clock.now() == hold
        clock.release()
        await asyncio.wait_for(sleeper, 5.0)
        assert clock.now() >= hold + 0.5

    asyncio.run(scenario())
    clock.close()


def test_a_file_that_is_not_a_clock_is_refused_naming_the_setting(tmp_path):
    bad = tmp_path / "clock"
    bad.write_bytes(b"hello world, this is not a clock file at all" * 2)
    with pytest.raises(ValueError, match="not a companion clock file"):
        SharedClock.open(str(bad))
    for path in (bad, tmp_path / "missing"):
        cfg = replace_config(CompanionConfig(), **{"sim.clock_file": str(path)})
        with pytest.raises(ConfigError, match=r"'sim\.clock_file'.*" + path.name):
            clock_from_config(cfg)


def test_time_waits_for_the_oldest_frame_each_worker_has_not_finished_by_its_own_lead(tmp_path):
    clock = SharedClock.create(str(tmp_path / "clock"), speedup=100.0)
    step = FrameLockstep(clock, PERIOD_S, {"mapper": MAPPER_LEAD_PERIODS, "flow": 6.5})
    t0 = clock.now() + 1.0  # frames captured 1 s of clock time (10 ms of wall time) ahead: the holds lie ahead
    first, second = _frame(1, t0), _frame(2, t0 + PERIOD_S)
    step.captured(first)
    step.captured(second)
    time.sleep(0.05)  # 5 s of clock time unheld
    assert clock.now() == pytest.approx(t0 + MAPPER_LEAD_PERIODS * PERIOD_S) and clock.held  # the mapper's lead
    step.finished(first, "mapper")
    time.sleep(0.05)
    assert clock.now() == pytest.approx(t0 + (1 + MAPPER_LEAD_PERIODS) * PERIOD_S)  # the second frame's
    step.finished(second, "mapper")
    time.sleep(0.05)
    assert clock.now() == pytest.approx(t0 + 6.5 * PERIOD_S)  # the flow may lag further, not for ever
    assert step.status()["outstanding"] == {"mapper": 0, "flow": 2}
    step.finished(first, "flow")
    step.finished(first, "flow")  # a second call for the same frame changes nothing
    time.sleep(0.05)
    assert clock.now() == pytest.approx(t0 + 7.5 * PERIOD_S)
    step.finished(second, "flow")
    assert not clock.held and step.status()["frames_held"] == {"mapper": 2, "flow": 2}
    time.sleep(0.05)
    assert clock.now() > t0 + 2.0  # nothing outstanding: time runs free
    clock.close()


def test_a_frame_a_full_queue_drops_no_longer_holds_the_clock(tmp_path):
    clock = SharedClock.create(str(tmp_path / "clock"), speedup=100.0)
    step = FrameLockstep(clock, PERIOD_S, {"mapper": MAPPER_LEAD_PERIODS})
    queue = FrameQueue(maxlen=1)
    t0 = clock.now() + 1.0
    old, new = _frame(1, t0), _frame(2, t0 + PERIOD_S)
    step.captured(old)
    assert queue.put(old) is None
    step.captured(new)
    dropped = queue.put(new)
    assert dropped is old
    step.finished(dropped, "mapper")  # what the daemon does with a dropped frame
    time.sleep(0.05)
    assert clock.now() == pytest.approx(t0 + (1 + MAPPER_LEAD_PERIODS) * PERIOD_S)  # the kept frame holds it
    step.close()  # the service stops: the simulation must not wait for it
    assert not clock.held
    time.sleep(0.05)
    assert clock.now() > t0 + 2.0
    step.captured(_frame(3, clock.now()))  # a frame after close does not hold it again
    assert not clock.held
    clock.close()


def test_the_simulator_waits_at_the_hold_of_its_clock_file(tmp_path):
    """``companion sim --clock-file``: the vehicle's own time (ATTITUDE's time_boot_ms, over real
    MAVLink on loopback) stops at a hold another process sets, and goes on once it is released."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    from drivers.sim.harness import MavClient, SimVehicleProcess

    path = tmp_path / "clock"
    client = MavClient.udp_listener()
    try:
        with SimVehicleProcess(["--udp-out", f"127.0.0.1:{client.port}", "--speedup", "5", "--clock-file", str(path)]):
            assert client.wait_heartbeat() is not None
            client.set_interval(mav.MAVLINK_MSG_ID_ATTITUDE, 20.0)
            clock = SharedClock.open(str(path))
            assert clock.speedup == 5.0
            hold = clock.now() + 1.0
            clock.hold_at(hold)
            # Every ATTITUDE up to the hold, then none newer: read until the stream dries up.
            newest = 0.0
            while (m := client.recv("ATTITUDE", timeout_s=1.0)) is not None:
                newest = m.time_boot_ms / 1000.0
                assert newest <= hold + 1e-3, f"the vehicle's time {newest} s passed the hold {hold} s"
            assert newest >= hold - 0.2  # it ran up to the hold (a 20 Hz stream: within one interval and a step)
            clock.release()
            m = client.recv("ATTITUDE", timeout_s=5.0, condition=lambda m: m.time_boot_ms / 1000.0 > hold + 0.5)
            assert m is not None, "the vehicle's time did not go on after the release"
            clock.close()
    finally:
        client.close()


def test_the_simulator_refuses_a_clock_file_it_cannot_create(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sim", "--duration", "1", "--tcp-listen", "127.0.0.1:0",
                           "--clock-file", str(tmp_path / "missing" / "clock")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert "--clock-file" in proc.stderr and "missing" in proc.stderr
