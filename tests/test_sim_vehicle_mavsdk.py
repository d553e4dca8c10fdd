"""A MAVLink implementation this project did not write (MAVSDK 4.x, native binding) flies the simulator.

MAVSDK connects unmodified over TCP, reads telemetry, arms, takes off and flies velocity setpoints:
OFFBOARD on the PX4 flavour, GUIDED on the ArduPilot flavour (MAVSDK maps its offboard API to GUIDED
for ArduPilot, see MAVSDK system_impl.cpp flight_mode_to_ardupilot_copter_mode).
"""

import time

import pytest

from drivers.sim.harness import SimVehicleProcess

mavsdk = pytest.importorskip("mavsdk", reason="mavsdk (native binding) is not installed")
from mavsdk import ComponentType, Configuration, Mavsdk  # noqa: E402
from mavsdk.plugins.action import Action  # noqa: E402
from mavsdk.plugins.offboard import Offboard, VelocityNedYaw  # noqa: E402
from mavsdk.plugins.telemetry import FlightMode, Telemetry  # noqa: E402


def wait_for(predicate, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_mavsdk_connects_reads_telemetry_arms_takes_off_and_flies_velocity_setpoints(flavour):
    with SimVehicleProcess(["--flavour", flavour, "--tcp-listen", "127.0.0.1:0", "--speedup", "4",
                            "--origin-delay", "0.5", "--seed", "2"]) as sim:
        m = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        try:
            assert m.add_any_connection(f"tcpout://127.0.0.1:{sim.endpoints['tcp']}").name == "SUCCESS"
            system = m.first_autopilot(10.0)
            assert system is not None, "MAVSDK did not discover the simulated autopilot"
            assert system.autopilot_type().name == ("PX4" if flavour == "px4" else "ARDUPILOT")
            tel, action, offboard = Telemetry(system), Action(system), Offboard(system)
            if flavour == "ardupilot":
                # ArduPilot streams nothing until asked; MAVSDK asks with SET_MESSAGE_INTERVAL
                for set_rate in (tel.set_rate_position, tel.set_rate_position_velocity_ned, tel.set_rate_in_air):
                    set_rate(10.0)
            wait_for(lambda: tel.health().is_home_position_ok and tel.health().is_local_position_ok, 10, "home and position")
            home = tel.home()
            assert abs(home.latitude_deg - 47.397742) < 1e-4  # the default scenario's home

            action.arm()
            wait_for(tel.armed, 5, "armed")
            action.takeoff()
            wait_for(lambda: tel.in_air() and tel.position().relative_altitude_m > 1.8, 10, "takeoff to ~2 m")

            offboard.set_velocity_ned(VelocityNedYaw(2.0, 0.0, 0.0, 0.0))
            offboard.start()
            wait_for(lambda: tel.flight_mode() == FlightMode.OFFBOARD, 5, "offboard/guided mode")
            pv = wait_for(lambda: (lambda x: x if x.position.north_m > 4.0 else None)(tel.position_velocity_ned()),
                          10, "4 m flown north")
            v = tel.velocity_ned()
            print(f"\nMAVSDK {flavour}: velocity {v.north_m_s:.2f} {v.east_m_s:.2f} {v.down_m_s:.2f} m/s, "
                  f"position {pv.position.north_m:.1f} {pv.position.east_m:.1f} {pv.position.down_m:.1f} m")
            assert abs(v.north_m_s - 2.0) < 0.3 and abs(v.east_m_s) < 0.3 and abs(v.down_m_s) < 0.3

            offboard.stop()
            wait_for(lambda: tel.flight_mode() == FlightMode.HOLD, 5, "hold after offboard stop")
            action.land()
            wait_for(lambda: not tel.armed(), 20, "landed and disarmed")
        finally:
            m.destroy()
        assert sim.stop() == 0
