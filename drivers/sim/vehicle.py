"""``companion sim``: a simulated multirotor that speaks MAVLink like ArduPilot Copter or PX4.

    companion sim --flavour ardupilot --scenario default --udp-out 127.0.0.1:14550
    companion sim --flavour px4 --tcp-listen 127.0.0.1:0 --speedup 10 --seed 3

Links (any number of each): ``--udp-out HOST:PORT`` sends to a GCS/companion listening with
``udpin`` (like SITL ``--out``), ``--udp-in HOST:PORT`` listens and answers the last sender,
``--tcp-listen HOST:PORT`` serves one TCP client at a time (like SITL's port 5760). With port 0 an
ephemeral port is bound; every endpoint prints one machine-readable line on stdout, e.g.
``LISTENING tcp 127.0.0.1:40521`` or ``SENDING udp 127.0.0.1:14550 from port 51234``.

Pacing: a fixed physics step (``sim.physics_rate_hz``) in simulated time, kept in step with a
:class:`drivers.clock.Clock` running ``--speedup`` times faster than the wall clock. Streams go
out at their requested rates in simulated time; ``time_boot_ms`` / ``time_usec`` are simulated
time since boot. If the machine cannot keep up, the simulation slows down (simulated time stays
consistent, it just runs slower than requested) and the slips are counted and logged. Received
messages are applied between physics steps, so given a seed the physics is deterministic for the
same commands at the same simulated times. With ``--clock-file`` the clock is a
:class:`drivers.clock.SharedClock` the service (``sim.clock_file``) reads and holds while its
mapper is behind: lockstep, so a slow host slows the flight down instead of costing frames.

SIGTERM / SIGINT end it cleanly (exit status 0).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import logging
import math
import signal
import sys
import time

import yaml

from companion.config import CompanionConfig, ConfigError, config_from_dict, load_config
from drivers.addresses import parse_host_port
from drivers.clock import Clock, SharedClock
from drivers.sim.autopilot import Home, SimAutopilot
from drivers.sim.mavlink_endpoint import Link, TcpListenEndpoint, UdpInEndpoint, UdpOutEndpoint

log = logging.getLogger("companion.sim")

TICK_WALL_S = 0.002          # how often the loop wakes to step physics and serve sockets
MAX_STEPS_PER_TICK = 800     # bound on work between two looks at the sockets
MAX_BEHIND_WALL_S = 0.25     # further behind the clock than this (wall time): slow the simulation down


def make_autopilot(sim, home: Home | None = None, sysid: int = 1, seed: int | None = None) -> SimAutopilot:
    """The simulated autopilot of flavour ``sim.flavour``."""
    if sim.flavour == "ardupilot":
        from drivers.sim.ardupilot import ArduPilotCopter
        return ArduPilotCopter(sim, home, sysid, seed)
    if sim.flavour == "px4":
        from drivers.sim.px4 import PX4Multicopter
        return PX4Multicopter(sim, home, sysid, seed)
    raise ValueError(f"unknown autopilot flavour {sim.flavour!r} (ardupilot or px4)")


def home_from_scenario(scenario: str) -> Home:
    """Home (origin lat/lon/alt and the ground under the start point) from the scenario's world.

    The vehicle needs nothing else from the world. Falls back to the built-in default home when
    the world module is not available in this build.
    """
    try:
        from drivers.sim.world import World
    except ModuleNotFoundError as exc:
        if exc.name and exc.name.startswith("drivers.sim.world"):
            log.warning("no world module: using the default home")
            return Home()
        raise
    world = World.load(scenario)
    h = world.home
    ground = float(world.terrain_height(0.0, 0.0))
    return Home(float(h.lat_deg), float(h.lon_deg), float(h.alt_m), start_down_m=-ground)


# ------------------------------------------------------------------------------------------------
# the simulation loop
# ------------------------------------------------------------------------------------------------


class VehicleProcess:
    """Owns the autopilot, its links and the pacing; ``run`` until ``stop`` is set."""

    def __init__(self, autopilot: SimAutopilot, endpoints: list, speedup: float, duration_s: float | None = None,
                 camera=None, clock: Clock | None = None):
        self.ap = autopilot
        self.camera = camera  # drivers.sim.camera_server.CameraServer or None
        self.endpoints = endpoints
        self.links = {e.link.name: e.link for e in endpoints}
        self.clock = clock or Clock(speedup)  # a SharedClock with --clock-file (lockstep with the service)
        self.duration_s = duration_s
        self.offset_s = 0.0     # simulated seconds the simulation has fallen behind the clock
        self.slips = 0
        self.build_errors = 0

    def _serve_inbound(self) -> None:
        for link in self.links.values():
            while link.inbound:
                self.ap.handle(link.inbound.popleft(), link)
        self._flush_outbox()

    def _flush_outbox(self) -> None:
        if not self.ap.outbox:
            return
        out, self.ap.outbox = self.ap.outbox, []
        for name, msg in out:
            if name is None:
                for link in self.links.values():
                    link.send(msg)
            elif name in self.links:
                self.links[name].send(msg)

    def _send_due(self) -> None:
        t = self.ap.t_s
        for link in self.links.values():
            for msg_id in link.schedule.pop_due(t):
                if link.connected:
                    try:
                        msg = self.ap.build(msg_id)
                    except Exception:  # noqa: BLE001 - a broken builder must not stop the others
                        self.build_errors += 1
                        log.exception("could not build message %d", msg_id)
                        link.schedule.set_interval(msg_id, None, t)
                        continue
                    if msg is not None:
                        link.send(msg)

    def advance(self, target_s: float) -> int:
        """Step physics up to ``target_s`` (at most MAX_STEPS_PER_TICK steps), sending due streams."""
        ap = self.ap
        steps = 0
        earliest = min((l.schedule.earliest_due_s for l in self.links.values()), default=math.inf)
        camera = self.camera
        while ap.t_s + ap.dt <= target_s + 1e-12 and steps < MAX_STEPS_PER_TICK:
            ap.step()
            steps += 1
            if camera is not None:
                camera.tick(ap.t_s, self._true_pose)
            if ap.t_s >= earliest - 1e-9:
                self._send_due()
                earliest = min((l.schedule.earliest_due_s for l in self.links.values()), default=math.inf)
            if ap.outbox:
                self._flush_outbox()
        return steps

    def _true_pose(self):
        return self.ap.vehicle.p, self.ap.vehicle.rotation_body_to_ned()

    async def run(self, stop: asyncio.Event) -> None:
        speedup = self.clock.speedup
        while not stop.is_set():
            self._serve_inbound()
            target = self.clock.now() - self.offset_s
            self.advance(target)
            behind = target - self.ap.t_s
            if behind > MAX_BEHIND_WALL_S * speedup:
                # cannot keep up: let simulated time run slower instead of piling up steps
                self.offset_s += behind
                self.slips += 1
                if self.slips in (1, 10, 100) or self.slips % 1000 == 0:
                    log.warning("simulation behind the clock by %.2f s (sim); slowed down (%d times)", behind, self.slips)
            if self.duration_s is not None and self.ap.t_s >= self.duration_s:
                break
            await asyncio.sleep(TICK_WALL_S)


async def _run(args, sim, home: Home) -> int:
    clock = None
    if args.clock_file:
        try:
            clock = SharedClock.create(args.clock_file, sim.speedup)
        except OSError as exc:
            print(f"companion sim: --clock-file: cannot create {args.clock_file}: {exc.strerror or exc}", file=sys.stderr)
            return 1
    ap = make_autopilot(sim, home, args.sysid)
    endpoints = []
    for i, spec in enumerate(args.udp_out or []):
        endpoints.append(UdpOutEndpoint(Link(f"udp-out{i}", args.sysid), parse_host_port(spec, "--udp-out")))
    for i, spec in enumerate(args.udp_in or []):
        endpoints.append(UdpInEndpoint(Link(f"udp-in{i}", args.sysid), parse_host_port(spec, "--udp-in")))
    for i, spec in enumerate(args.tcp_listen or []):
        endpoints.append(TcpListenEndpoint(Link(f"tcp{i}", args.sysid), parse_host_port(spec, "--tcp-listen")))
    for e in endpoints:
        e.link.schedule = ap.initial_schedule()
    try:
        for e in endpoints:
            await e.start()
    except OSError as exc:
        print(f"companion sim: cannot open a link: {exc}", file=sys.stderr)
        for e in endpoints:
            e.close()
        return 1
    camera = None
    if args.camera_listen:
        from drivers.sim.camera_server import camera_server_from_config

        cfg = load_config(args.config) if args.config else CompanionConfig()
        cfg = dataclasses.replace(cfg, sim=sim)
        host, port = parse_host_port(args.camera_listen, "--camera-listen")
        camera = camera_server_from_config(cfg, host, port, args.camera_rate)
        try:
            await camera.start()
        except OSError as exc:
            print(f"companion sim: cannot open the camera stream: {exc}", file=sys.stderr)
            camera.close()
            for e in endpoints:
                e.close()
            return 1
        endpoints_lines = [camera.describe()]
    else:
        endpoints_lines = []
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)  # before announcing: a client may signal at once
    for e in endpoints:
        print(e.describe(), flush=True)
    for line in endpoints_lines:
        print(line, flush=True)
    process = VehicleProcess(ap, endpoints, sim.speedup, args.duration, camera, clock)
    log.info("%s vehicle sysid %d, speed-up %.1f, seed %d, origin after %.1f s, home %.6f %.6f %.1f m",
             ap.FLAVOUR, args.sysid, sim.speedup, ap.seed, sim.origin_delay_s, home.lat_deg, home.lon_deg, home.alt_m)
    wall0 = time.monotonic()
    try:
        await process.run(stop)
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(sig)
        for e in endpoints:
            e.close()
        if camera is not None:
            camera.close()
            log.info("camera stream: %d frames, %d ticks skipped (render busy), %d sends dropped (client behind), "
                     "%d render errors", camera.frames_sent, camera.skipped_ticks, camera.dropped_sends,
                     camera.render_errors)
    wall = time.monotonic() - wall0
    sent = sum(l.sent for l in process.links.values())
    log.info("stopped at t=%.1f s simulated after %.1f s wall (x%.1f), %d messages sent, %d setpoints received "
             "(%d ignored), %d slips, unhandled %s", ap.t_s, wall, ap.t_s / wall if wall > 0 else 0.0, sent,
             ap.setpoints_received, ap.setpoints_ignored, process.slips, dict(ap.unhandled))
    return 0


# ------------------------------------------------------------------------------------------------
# command line
# ------------------------------------------------------------------------------------------------


def configure_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--flavour", choices=("ardupilot", "px4"), help="autopilot to imitate (default: sim.flavour)")
    p.add_argument("--config", metavar="FILE", help="companion YAML configuration; its sim: section is used")
    p.add_argument("--scenario", help="scenario name or YAML path (home position and ground height)")
    p.add_argument("--udp-out", action="append", metavar="HOST:PORT", help="send to a udpin listener (repeatable)")
    p.add_argument("--udp-in", action="append", metavar="HOST:PORT", help="listen for UDP, answer the last sender")
    p.add_argument("--tcp-listen", action="append", metavar="HOST:PORT", help="TCP server, one client at a time")
    p.add_argument("--speedup", type=float, help="simulated seconds per wall second (default: sim.speedup)")
    p.add_argument("--seed", type=int, help="random seed of navigation error, GPS and wind (default: sim.seed)")
    p.add_argument("--sysid", type=int, default=1, help="MAVLink system id (default 1)")
    p.add_argument("--origin-delay", type=float, metavar="S", help="EKF origin / GPS fix this long after boot")
    p.add_argument("--home", metavar="LAT,LON,ALT",
                   help="override the scenario's home (deg, deg, m AMSL); write --home=-35.36,149.17,584 for a negative latitude")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override any sim.* key, e.g. nav_vel_sigma_mps=0.5")
    p.add_argument("--clock-file", metavar="FILE",
                   help="lockstep: create a shared clock here for the service (sim.clock_file), which holds it while its "
                        "mapper is behind (docs/sim.md)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after this many simulated seconds")
    p.add_argument("--camera-listen", metavar="HOST:PORT",
                   help="serve the vehicle's camera as a frame stream (camera.source: stream; port 0 = ephemeral)")
    p.add_argument("--camera-rate", type=float, metavar="HZ", help="frame stream rate in simulated Hz (default: camera.rate_hz)")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))


def sim_config_from_args(args) -> tuple:
    """(SimConfig, Home) from --config, --set and the explicit options; ConfigError/ValueError on bad input."""
    cfg = load_config(args.config) if args.config else CompanionConfig()
    overrides: dict = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set: expected KEY=VALUE, got {item!r}")
        overrides[key.strip().removeprefix("sim.")] = yaml.safe_load(value)
    for key, value in (("flavour", args.flavour), ("scenario", args.scenario), ("speedup", args.speedup),
                       ("seed", args.seed), ("origin_delay_s", args.origin_delay)):
        if value is not None:
            overrides[key] = value
    base = {f.name: getattr(cfg.sim, f.name) for f in dataclasses.fields(cfg.sim)}
    base = {k: list(v) if isinstance(v, tuple) else v for k, v in base.items()}
    base.update(overrides)
    sim = config_from_dict({"sim": base}, "command line").sim
    if not 1 <= args.sysid <= 255:
        raise ConfigError(f"--sysid must be in 1..255, got {args.sysid}")
    home = home_from_scenario(sim.scenario)
    if args.home:
        parts = args.home.split(",")
        if len(parts) != 3:
            raise ConfigError(f"--home: expected LAT,LON,ALT, got {args.home!r}")
        try:
            lat, lon, alt = (float(x) for x in parts)
        except ValueError:
            raise ConfigError(f"--home: LAT,LON,ALT must be numbers, got {args.home!r}") from None
        home = Home(lat, lon, alt, home.start_down_m)
    return sim, home


def main(args: argparse.Namespace) -> int:
    logging.basicConfig(level=getattr(logging, args.log_level), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if not (args.udp_out or args.udp_in or args.tcp_listen):
        print("companion sim: give at least one link: --udp-out, --udp-in or --tcp-listen", file=sys.stderr)
        return 2
    try:
        sim, home = sim_config_from_args(args)
        for spec, what in [(s, "--udp-out") for s in args.udp_out or []] + [(s, "--udp-in") for s in args.udp_in or []] \
                + [(s, "--tcp-listen") for s in args.tcp_listen or []]:
            parse_host_port(spec, what)
        if args.camera_listen:
            parse_host_port(args.camera_listen, "--camera-listen")
        if args.camera_rate is not None and not (0.5 <= args.camera_rate <= 500.0):
            raise ConfigError(f"--camera-rate must be within 0.5..500 Hz, got {args.camera_rate}")
    except (ConfigError, ValueError) as exc:
        print(f"companion sim: {exc}", file=sys.stderr)
        return 2
    return asyncio.run(_run(args, sim, home))
