"""A fleet through one router on loopback: ``companion router`` as its own process, five vehicles
publishing maps as the service does (deflated tiles, status, avoidance) and two ground-station
sessions subscribed to every vehicle's tiles through the router. Every tile reaches both stations
(none lost, none undecodable) and both see all five vehicles. Latency is printed, not asserted:
benchmarks/fleet_bench.py measures it against the fleet's size (docs/zenoh.md)."""

from __future__ import annotations

import pytest

from benchmarks.fleet_bench import Router, run_fleet


@pytest.mark.slow
def test_five_vehicles_and_two_ground_stations_through_one_router_lose_nothing():
    router = Router()
    try:
        r = run_fleet(5, 3.0, router.endpoint, router.proc.pid)
    finally:
        router.close()
    print(f"\n5 vehicles, 2 stations: {r['tiles_published']} tiles published, {r['tiles_received']} received, "
          f"latency p50 {r['latency_p50_ms']:.2f} ms p99 {r['latency_p99_ms']:.2f} ms, router {r['router_cpu_percent']} % "
          f"of a core, {r['router_rss_mb']} MB")
    assert r["tiles_published"] >= 5 * 3 * 3  # about 4 a second per vehicle
    assert r["loss"] == 0 and r["bad"] == 0 and r["tiles_received"] == 2 * r["tiles_published"]
    assert r["vehicles_seen"] == [5, 5]
    assert r["tile_bytes_mean"] < 12_320 / 2  # deflated
    assert router.proc.returncode == 0  # the router stopped cleanly on SIGTERM
