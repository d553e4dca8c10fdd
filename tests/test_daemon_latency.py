"""The daemon's latency path: the mapper in its own process computes what the mapper in
this process computes, survives a failing step and a dead child, and every frame whose map update
reached the grid gets exactly one frame-to-setpoint sample, taken at the first setpoint whose law
read that update (held back while there is no setpoint to give)."""

from __future__ import annotations

import asyncio
import sys
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/ is not an installed package
from benchmarks.common import render_flight  # noqa: E402
from companion.config import CompanionConfig, replace  # noqa: E402
from companion.method.mapper import Mapper  # noqa: E402
from companion.method.messages import NavState  # noqa: E402
from companion.method.terrain.grid import TerrainGrid  # noqa: E402
from companion.service.daemon import Daemon  # noqa: E402
from companion.service.mapper_process import MapperProcess, MapperProcessError  # noqa: E402


def steps_equal(a, b) -> None:
    for name in ("matched_ids", "matched_measurements", "initialised_ids", "initialised_measurements", "removed_ids"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(a.points.feature_ids, b.points.feature_ids)
    np.testing.assert_array_equal(a.points.positions_ned_m, b.points.positions_ned_m)
    np.testing.assert_array_equal(a.points.covariances, b.points.covariances)
    assert (a.n_measurements, a.n_active, a.n_prior_fallback) == (b.n_measurements, b.n_active, b.n_prior_fallback)


def test_the_mapper_process_steps_as_the_mapper_in_this_process():
    cfg = CompanionConfig()
    flight = render_flight(40, cfg)
    # the daemon's map, with some terrain already in it (the depth prior reads it)
    grid = TerrainGrid.from_config(cfg.terrain)
    here_grid = TerrainGrid.from_config(cfg.terrain)

    def with_map(use):
        use(grid)

    local = Mapper(cfg.mapper, flight.camera, flight.mount,
                   depth_prior=lambda o, r: here_grid.ray_range(o, r, cfg.mapper.prior_max_range_m),
                   default_ground_alt_m=cfg.terrain.default_ground_alt_m, border_px=cfg.camera.border_px)
    child = MapperProcess(cfg, with_map)
    try:
        converged = 0
        for nav, image in zip(flight.navs, flight.images):
            a, b = local.step(nav, image), child.step(nav, image)
            steps_equal(a, b)
            # both maps take the step's evidence, as the daemon and its child do
            here_grid.add_evidence(a.points, a.free_space, a.floors)
            grid.add_evidence(b.points, b.free_space, b.floors)
            converged += len(a.points)
        assert converged > 0 and child.starts == 1

        # a step that raises in the child is reported, and the child goes on
        with pytest.raises(MapperProcessError, match="ValueError"):
            child.step(flight.navs[0], np.zeros(5, np.uint8))
        assert child.alive and child.step(flight.navs[-1], flight.images[-1]).n_measurements > 0

        # a larger image (colour) needs a larger shared buffer: a new one is passed to the child
        colour = np.repeat(flight.images[-1][:, :, None], 3, axis=2)
        assert child.step(flight.navs[-1], colour).n_measurements > 0 and child._buffer.size == colour.nbytes

        # a dead child: the next step starts a new one from the daemon's map (no features yet)
        child._proc.kill()
        child._proc.wait(5)
        fresh = child.step(flight.navs[-1], flight.images[-1])
        assert child.starts == 2 and fresh.n_matched == 0 and fresh.n_initialised > 0
        # a child that dies during a step: that step says so
        child._conn.close()
        with pytest.raises(MapperProcessError, match="died"):
            child.step(flight.navs[-1], flight.images[-1])
        assert child.step(flight.navs[-1], flight.images[-1]).n_initialised > 0 and child.starts == 3
    finally:
        child.close()
    assert not child.alive


@pytest.fixture()
def daemon(tmp_path):
    cfg = replace(CompanionConfig(), **{"persistence.directory": str(tmp_path / "map"), "zenoh.enabled": False})
    return Daemon(cfg, mapper_process=False)


def fresh_nav(d: Daemon) -> NavState:
    return NavState(d.clock.now(), np.array([0.0, 0.0, -20.0]), np.array([5.0, 0.0, 0.0]), np.array([1.0, 0, 0, 0]),
                    np.eye(9) * 0.01)


def test_every_map_update_gets_one_frame_to_setpoint_sample_at_the_first_setpoint(daemon):
    d = daemon

    async def main():
        d._loop = asyncio.get_running_loop()
        loop_task = asyncio.create_task(d._control_loop())
        try:
            # Two updates while there is no navigation: no setpoint, so no sample yet; they wait.
            now = d.clock.now()
            with d.grid_lock:
                d._map_updates.extend([now - 0.030, now - 0.020])
            d._map_updated.set()
            await asyncio.sleep(0.15)
            assert d.frame_to_setpoint_ms.summary()["n"] == 0 and len(d._map_updates) == 2
            assert d.command_state == "no navigation yet"

            # Navigation arrives: the next step gives a setpoint (advisory here) that used both.
            d.link.nav_buffer.push(fresh_nav(d))
            await asyncio.sleep(0.08)
            s = d.frame_to_setpoint_ms.summary()
            assert s["n"] == 2 and len(d._map_updates) == 0
            assert s["max"] >= 170.0  # the 30 ms old frame waited 150 ms more for a setpoint

            # A new update wakes the loop at once: one sample, a few ms after the frame.
            d.link.nav_buffer.push(fresh_nav(d))
            t_frame = d.clock.now() - 0.005
            t0 = time.monotonic()
            with d.grid_lock:
                d._map_updates.append(t_frame)
            d._map_updated.set()
            while d.frame_to_setpoint_ms.summary()["n"] < 3 and time.monotonic() - t0 < 1.0:
                await asyncio.sleep(0.001)
            waited_ms = (time.monotonic() - t0) * 1e3
            samples = [v for _, v in d.frame_to_setpoint_ms.values]
            assert len(samples) == 3
            assert 5.0 <= samples[-1] <= 5.0 + waited_ms + 1.0
            assert waited_ms < 40.0  # not the next 50 ms tick: woken by the update
        finally:
            d._stop.set()
            await asyncio.wait_for(loop_task, 1.0)

    asyncio.run(main())
    assert d.control_ticks > 0
    assert d.control_jitter_ms.summary()["n"] == d.control_ticks


def test_the_frame_queue_is_idle_only_when_its_worker_has_finished_every_frame():
    """The dense flow's thread waits for the mapper's queue to be idle before a measured frame's
    flows: a frame put makes it busy, the worker's ``done`` after a frame makes it idle again only
    when no other frame waits, and a waiting thread wakes when it does."""
    import threading

    from companion.method.messages import Frame
    from companion.service.daemon import FrameQueue

    q = FrameQueue(maxlen=2)
    assert q.idle.is_set()
    frames = [Frame(t_s=float(k), image=np.zeros((4, 4), np.uint8), sequence=k) for k in range(2)]
    q.put(frames[0])
    q.put(frames[1])
    assert not q.idle.is_set()
    woke = threading.Event()
    waiter = threading.Thread(target=lambda: q.idle.wait(10.0) and woke.set())
    waiter.start()
    assert q.get(0.1) is frames[0]
    q.done()
    assert not q.idle.is_set()  # the second frame still waits
    assert q.get(0.1) is frames[1]
    q.done()
    waiter.join(10.0)
    assert q.idle.is_set() and woke.is_set()
