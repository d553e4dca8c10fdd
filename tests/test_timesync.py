"""Autopilot -> companion time: TIMESYNC round trips, SYSTEM_TIME arrivals, reboots and jumps."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.method.navigation.timesync import TimeSync

TRUE_OFFSET = 123.456  # companion - autopilot (s)


def roundtrips(ts: TimeSync, rng, n, t0=1000.0, up=(0.001, 0.004), down=(0.001, 0.004), offset=TRUE_OFFSET):
    """Feed n TIMESYNC exchanges with random one-way delays; return the RTTs."""
    rtts = []
    t = t0
    for _ in range(n):
        d_up = up[0] + rng.exponential(up[1])
        d_down = down[0] + rng.exponential(down[1])
        t_remote = t + d_up - offset  # the autopilot stamps when the request arrives
        t_recv = t + d_up + d_down
        ts.add_roundtrip(t, t_remote, t_recv)
        rtts.append(d_up + d_down)
        t += 1.0
    return np.array(rtts)


def test_roundtrips_estimate_offset_within_the_best_round_trips():
    ts = TimeSync(window=32)
    rng = np.random.default_rng(1)
    rtts = roundtrips(ts, rng, 40)
    err = ts.offset_s - TRUE_OFFSET
    window_rtts = np.sort(rtts[-32:])
    bound = window_rtts[len(window_rtts) // 4 - 1] / 2  # worst of the best quarter, halved
    assert abs(err) <= bound
    assert abs(err) < 0.002
    assert ts.source == "TIMESYNC"
    assert ts.rtt_s == pytest.approx(np.median(window_rtts), rel=1e-9)
    assert 0 < ts.jitter_s < 0.01
    assert ts.to_companion(10.0) == pytest.approx(10.0 + ts.offset_s)


def test_burst_of_slow_replies_does_not_move_the_estimate():
    ts = TimeSync(window=32)
    rng = np.random.default_rng(2)
    roundtrips(ts, rng, 32)
    before = ts.offset_s
    # 10 replies delayed 200 ms on the way back only (a busy radio): each biased by +100 ms
    roundtrips(ts, rng, 10, t0=2000.0, down=(0.2, 0.001))
    assert abs(ts.offset_s - before) < 0.002
    assert ts.jitter_s > 0.0


@settings(deadline=None, max_examples=40)
@given(
    offset=st.floats(-1e5, 1e5),
    d_up=st.floats(0.0, 0.2),
    d_down=st.floats(0.0, 0.2),
)
def test_error_never_exceeds_half_the_round_trip(offset, d_up, d_down):
    ts = TimeSync(window=8)
    for i in range(8):
        t = 50.0 + i
        ts.add_roundtrip(t, t + d_up - offset, t + d_up + d_down)
    assert abs(ts.offset_s - offset) <= (d_up + d_down) / 2 + 1e-6


def test_round_trips_too_slow_or_negative_are_rejected_and_counted():
    ts = TimeSync(max_rtt_s=0.5)
    assert not ts.add_roundtrip(10.0, 0.0, 11.0)
    assert not ts.add_roundtrip(10.0, 0.0, 9.0)
    assert not ts.add_roundtrip(10.0, float("nan"), 10.01)
    assert ts.rejected == 3 and not ts.synced and ts.to_companion(1.0) is None


def test_one_way_arrivals_give_a_late_biased_bound_until_round_trips_arrive():
    ts = TimeSync(window=16)
    rng = np.random.default_rng(3)
    d_min = 0.002
    for i in range(16):
        t_remote = 10.0 + i
        ts.add_one_way(t_remote, t_remote + TRUE_OFFSET + d_min + rng.exponential(0.01))
    assert ts.source == "SYSTEM_TIME"
    assert TRUE_OFFSET + d_min <= ts.offset_s < TRUE_OFFSET + d_min + 0.01
    roundtrips(ts, rng, 8, t0=TRUE_OFFSET + 30.0)
    assert ts.source == "TIMESYNC"
    assert abs(ts.offset_s - TRUE_OFFSET) < 0.003


def test_reboot_resets_and_the_new_offset_is_learnt():
    ts = TimeSync(window=8)
    rng = np.random.default_rng(4)
    roundtrips(ts, rng, 8, t0=1000.0)
    assert abs(ts.offset_s - TRUE_OFFSET) < 0.003
    # The autopilot reboots at companion time ~1100: its clock restarts near zero.
    new_offset = 1100.0
    assert ts.observe_remote_time(2.0)
    assert ts.reboots == 1 and not ts.synced
    roundtrips(ts, rng, 8, t0=1102.0, offset=new_offset)
    assert abs(ts.offset_s - new_offset) < 0.003
    assert ts.reboots == 1


def test_small_backwards_steps_are_not_reboots():
    ts = TimeSync(reboot_threshold_s=1.0)
    assert not ts.observe_remote_time(100.0)
    assert not ts.observe_remote_time(99.5)  # out-of-order message
    assert ts.reboots == 0


def test_single_outlier_ignored_persistent_jump_resets():
    ts = TimeSync(window=16, jump_threshold_s=0.5, jump_confirmations=3)
    rng = np.random.default_rng(5)
    roundtrips(ts, rng, 16, t0=1000.0)
    roundtrips(ts, rng, 1, t0=1100.0, offset=TRUE_OFFSET - 5.0)  # one wild sample
    assert abs(ts.offset_s - TRUE_OFFSET) < 0.003
    resets = ts.resets
    roundtrips(ts, rng, 6, t0=1200.0, offset=TRUE_OFFSET - 5.0)  # the clock really moved
    assert ts.resets == resets + 1
    assert abs(ts.offset_s - (TRUE_OFFSET - 5.0)) < 0.003


def test_status_snapshot():
    ts = TimeSync()
    s = ts.status()
    assert s.source == "none" and s.offset_s is None and s.samples == 0
    roundtrips(ts, np.random.default_rng(6), 4)
    s = ts.status()
    assert s.source == "TIMESYNC" and s.samples == 4 and s.rtt_s > 0


# ---- stamps checked against the autopilot clock: one stray stamp is not a reboot -------------


def stamps(ts: TimeSync, t_local0: float, n: int, offset: float, step: float = 0.02) -> list[str]:
    """n stamps of an autopilot clock with ``companion - autopilot = offset``, one every ``step`` s."""
    return [ts.check_remote_time(t_local0 + i * step - offset, t_local0 + i * step) for i in range(n)]


def test_a_single_stray_stamp_behind_or_ahead_is_rejected_and_the_time_base_stays():
    ts = TimeSync()
    rng = np.random.default_rng(7)
    roundtrips(ts, rng, 8, t0=1000.0)
    assert stamps(ts, 1008.0, 5, TRUE_OFFSET) == ["ok"] * 5
    offset = ts.offset_s
    assert ts.check_remote_time(1008.1 - TRUE_OFFSET - 50.0, 1008.1) == "behind"  # a packet from an older boot
    assert ts.check_remote_time(1008.1 - TRUE_OFFSET + 3600.0, 1008.1) == "ahead"  # a corrupt stamp
    assert stamps(ts, 1008.2, 5, TRUE_OFFSET) == ["ok"] * 5
    assert ts.reboots == 0 and ts.clock_jumps == 0 and ts.offset_s == offset
    assert ts.outliers == {"behind": 1, "ahead": 1}
    # Stray stamps that do not agree with each other never add up to a reboot, even in a row.
    assert [ts.check_remote_time(t, 1009.0) for t in (5.0, 300.0, 77.0, 600.0)] == ["behind"] * 4
    assert ts.reboots == 0 and ts.synced


def test_consistent_stamps_behind_confirm_a_reboot_and_ahead_a_clock_jump():
    ts = TimeSync(jump_confirmations=3)
    roundtrips(ts, np.random.default_rng(8), 8, t0=1000.0)
    new_offset = 1010.0  # rebooted at companion time ~1010: its clock restarts near 0
    assert stamps(ts, 1010.5, 3, new_offset) == ["behind", "behind", "reboot"]
    assert ts.reboots == 1 and not ts.synced
    assert stamps(ts, 1010.6, 3, new_offset) == ["ok"] * 3  # the new clock is the reference now
    ts.add_one_way(1011.0 - new_offset - 0.001, 1011.0)
    assert ts.offset_s == pytest.approx(new_offset, abs=0.002)
    assert stamps(ts, 1012.0, 2, new_offset - 40.0) == ["ahead", "ahead"]  # a router now shows another autopilot
    assert stamps(ts, 1012.1, 1, new_offset - 40.0) == ["jump"] and ts.clock_jumps == 1 and ts.reboots == 1


def test_a_long_silence_is_not_a_jump_and_round_trips_off_the_clock_are_refused():
    ts = TimeSync()
    roundtrips(ts, np.random.default_rng(9), 8, t0=1000.0)
    assert stamps(ts, 1100.0, 1, TRUE_OFFSET) == ["ok"]  # 90 s without a word (link lost): both clocks ran on
    rejected = ts.rejected
    assert not ts.add_roundtrip(1101.0, 1101.0 - TRUE_OFFSET + 500.0, 1101.002)  # a TIMESYNC answer 500 s ahead
    assert ts.rejected == rejected + 1 and abs(ts.offset_s - TRUE_OFFSET) < 0.003
