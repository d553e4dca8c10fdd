"""Multirotor point-mass dynamics, flown by the cascade a real autopilot flies it with.

The vehicle is a point mass with a yaw angle. Its attitude is not integrated from torques: a
multirotor points its thrust where the position controller asks, so roll and pitch follow from
the commanded acceleration (tilt = atan(a_h / g)) through a short first-order lag that stands in
for the attitude loop. That is enough for a camera riding on the vehicle to pitch realistically
when it accelerates, and for wind to make it lean.

The controller is the structure ArduPilot's AC_PosControl and PX4's mc_pos_control share:

1. **Reference** (``shape_reference``): the setpoint is turned into a desired velocity ``v_t``
   (position error through a square-root controller, plus velocity feed-forward), and the
   reference velocity ``v_d`` moves toward it no faster than the acceleration limits allow.
   The reference position ``p_d`` integrates ``v_d``, so a velocity setpoint also holds position
   against drift, and a zero velocity becomes a position hold where the vehicle stopped
   (ArduPilot's "stabilise position" in GUIDED velocity control).
2. **Tracking** (``tracking_acceleration``): ``a_c = a_d + K_v (v_d + K_p (p_d - p) - v) + I``,
   tilt- and thrust-limited; the integrator ``I`` takes out steady wind.
3. **Plant** (``step``): ``a = a_thrust_lagged + g + k_drag (w - v)``; ground contact clamps the
   vehicle to the ground plane (landed = sitting on it).

Setpoints use PX4's trajectory_setpoint convention: per axis, NaN means "not controlled", so a
setpoint may mix position on one axis with velocity on another (``Setpoint``). Every quantity is
NED, SI units. The inner loop is plain Python floats: it runs at 400 Hz times the speed-up factor,
where per-call NumPy overhead would dominate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.method.geometry import matrix_to_quat

GRAVITY_MPS2 = 9.80665
NAN = float("nan")


def _finite(x: float) -> bool:
    return x == x and x not in (math.inf, -math.inf)


def wrap_pi(angle: float) -> float:
    """Angle wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True, slots=True)
class MultirotorLimits:
    """Limits and gains of the simulated position controller (SI units, see SimConfig for meaning)."""

    accel_h_mps2: float = 3.0
    accel_v_mps2: float = 2.5
    speed_h_mps: float = 15.0
    climb_mps: float = 5.0
    descent_mps: float = 3.0
    tilt_max_rad: float = math.radians(35.0)
    pos_gain_per_s: float = 1.0
    vel_gain_per_s: float = 2.5
    vel_int_gain_per_s2: float = 0.6
    int_limit_mps2: float = 4.0
    attitude_tau_s: float = 0.08
    yaw_rate_max_rps: float = math.radians(90.0)
    drag_per_s: float = 0.3
    thrust_max_g: float = 2.0  # maximum thrust in units of the weight

    def __post_init__(self) -> None:
        for name in ("accel_h_mps2", "accel_v_mps2", "speed_h_mps", "climb_mps", "descent_mps",
                     "tilt_max_rad", "pos_gain_per_s", "vel_gain_per_s", "attitude_tau_s", "yaw_rate_max_rps"):
            value = getattr(self, name)
            if not (_finite(value) and value > 0):
                raise ValueError(f"MultirotorLimits.{name} must be positive and finite, got {value!r}")
        if not self.tilt_max_rad < math.radians(80):
            raise ValueError(f"MultirotorLimits.tilt_max_rad must be below 80 deg, got {math.degrees(self.tilt_max_rad):.1f}")

    @classmethod
    def from_config(cls, sim) -> "MultirotorLimits":
        """From a :class:`companion.config.SimConfig`."""
        return cls(
            accel_h_mps2=sim.accel_h_mps2, accel_v_mps2=sim.accel_v_mps2, speed_h_mps=sim.speed_h_mps,
            climb_mps=sim.climb_mps, descent_mps=sim.descent_mps, tilt_max_rad=math.radians(sim.tilt_max_deg),
            pos_gain_per_s=sim.pos_gain_per_s, vel_gain_per_s=sim.vel_gain_per_s, drag_per_s=sim.drag_per_s,
        )


@dataclass(slots=True)
class Setpoint:
    """What the position controller is asked to do. Per-axis NaN = that axis is not controlled.

    position_ned_m, velocity_ned_mps, accel_ned_mps2: 3-tuples (north, east, down).
    An axis with neither position nor velocity holds the reference where it is (zero velocity).
    yaw_rad / yaw_rate_rps: NaN = not commanded; then ``yaw_follows_velocity`` turns the nose
    along the horizontal reference velocity (ArduPilot's default auto-yaw), else yaw holds.
    speed_h_mps / climb_mps / descent_mps: optional tighter limits for this setpoint (NaN = none),
    e.g. a takeoff climbs at the autopilot's takeoff speed, not the vehicle's maximum.
    """

    position_ned_m: tuple[float, float, float] = (NAN, NAN, NAN)
    velocity_ned_mps: tuple[float, float, float] = (NAN, NAN, NAN)
    accel_ned_mps2: tuple[float, float, float] = (NAN, NAN, NAN)
    yaw_rad: float = NAN
    yaw_rate_rps: float = NAN
    yaw_follows_velocity: bool = False
    speed_h_mps: float = NAN
    climb_mps: float = NAN
    descent_mps: float = NAN

    @classmethod
    def hold(cls, position_ned_m, yaw_rad: float = NAN) -> "Setpoint":
        return cls(position_ned_m=tuple(float(x) for x in position_ned_m), yaw_rad=yaw_rad)


def sqrt_controller(error_m: float, gain_per_s: float, accel_mps2: float) -> float:
    """Speed that closes a position error without exceeding ``accel_mps2`` when braking.

    Linear (``k e``) close in, ``sqrt(2 a (|e| - a / 2k^2))`` further out; continuous at the
    switch ``|e| = a / k^2``. The shape ArduPilot's AC_PosControl uses for its position loop.
    """
    e = abs(error_m)
    linear_limit = accel_mps2 / (gain_per_s * gain_per_s)
    speed = gain_per_s * e if e <= linear_limit else math.sqrt(2.0 * accel_mps2 * (e - 0.5 * linear_limit))
    return math.copysign(speed, error_m)


@dataclass(slots=True)
class PointMassMultirotor:
    """Truth state and controller state of the simulated vehicle.

    Truth: ``p`` position NED (m), ``v`` velocity NED (m/s), ``yaw`` (rad), ``thrust`` the lagged
    specific thrust vector NED (m/s^2, points up: about (0, 0, -g) in hover), ``landed``.
    Controller: reference ``p_d``, ``v_d`` (the shaped setpoint, in the estimate's frame) and the
    velocity integrator; ``err_p``, ``err_v`` the navigation error it flies with (estimate - truth).
    ``ground_down_m``: NED z of the ground plane under the vehicle.
    """

    limits: MultirotorLimits = field(default_factory=MultirotorLimits)
    ground_down_m: float = 0.0
    p: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    v: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    yaw: float = 0.0
    thrust: list[float] = field(default_factory=lambda: [0.0, 0.0, -GRAVITY_MPS2])
    accel: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    landed: bool = True
    p_d: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    v_d: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    a_d: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    integ: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    err_p: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    err_v: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    prev_thrust: list[float] = field(default_factory=lambda: [0.0, 0.0, -GRAVITY_MPS2])
    prev_yaw: float = 0.0
    last_dt: float = 0.0025

    def __post_init__(self) -> None:
        self.p[2] = min(self.p[2], self.ground_down_m)
        self.landed = self.p[2] >= self.ground_down_m - 1e-6
        self.reset_reference()

    # ---- controller ------------------------------------------------------------------------

    def estimate_offset(self, err_p, err_v) -> None:
        """The navigation error the controller flies with: it regulates ``p + err_p``, ``v + err_v``.

        A real autopilot controls its estimate, not the truth; zero offsets fly the truth.
        """
        self.err_p = [float(err_p[0]), float(err_p[1]), float(err_p[2])]
        self.err_v = [float(err_v[0]), float(err_v[1]), float(err_v[2])]

    def reset_reference(self) -> None:
        """Reference := estimate, integrator cleared (on the ground, or when a new mode takes over)."""
        self.p_d = [self.p[i] + self.err_p[i] for i in range(3)]
        self.v_d = [self.v[i] + self.err_v[i] for i in range(3)] if not self.landed else [0.0, 0.0, 0.0]
        self.a_d = [0.0, 0.0, 0.0]
        self.integ = [0.0, 0.0, 0.0]

    def target_velocity(self, sp: Setpoint) -> list[float]:
        """Desired velocity from the setpoint: sqrt controller on position error, plus feed-forward.

        Returns the limited (speed, climb, descent) velocity the reference steers toward.
        """
        lim = self.limits
        pos, vel, acc = sp.position_ned_m, sp.velocity_ned_mps, sp.accel_ned_mps2
        vt = [0.0, 0.0, 0.0]
        # Horizontal position acts on the error vector so that the approach is a straight line.
        ex = pos[0] - self.p_d[0] if _finite(pos[0]) else 0.0
        ey = pos[1] - self.p_d[1] if _finite(pos[1]) else 0.0
        eh = math.hypot(ex, ey)
        if eh > 0.0:
            s = sqrt_controller(eh, lim.pos_gain_per_s, lim.accel_h_mps2) / eh
            vt[0], vt[1] = s * ex, s * ey
        if _finite(pos[2]):
            vt[2] = sqrt_controller(pos[2] - self.p_d[2], lim.pos_gain_per_s, lim.accel_v_mps2)
        for i in range(3):
            if _finite(vel[i]):
                vt[i] += vel[i]
            elif not _finite(pos[i]) and _finite(acc[i]):
                # acceleration-only axis: the reference velocity integrates the acceleration
                vt[i] = self.v_d[i] + acc[i] * self.last_dt
        speed_h = min(lim.speed_h_mps, sp.speed_h_mps) if _finite(sp.speed_h_mps) else lim.speed_h_mps
        climb = min(lim.climb_mps, sp.climb_mps) if _finite(sp.climb_mps) else lim.climb_mps
        descent = min(lim.descent_mps, sp.descent_mps) if _finite(sp.descent_mps) else lim.descent_mps
        vh = math.hypot(vt[0], vt[1])
        if vh > speed_h:
            vt[0] *= speed_h / vh
            vt[1] *= speed_h / vh
        vt[2] = min(max(vt[2], -climb), descent)
        return vt

    def shape_reference(self, vt: list[float], dt: float) -> None:
        """Move ``v_d`` toward ``vt`` within the acceleration limits; integrate ``p_d``."""
        lim = self.limits
        dvx, dvy, dvz = vt[0] - self.v_d[0], vt[1] - self.v_d[1], vt[2] - self.v_d[2]
        dh = math.hypot(dvx, dvy)
        max_h = lim.accel_h_mps2 * dt
        if dh > max_h:
            dvx *= max_h / dh
            dvy *= max_h / dh
        max_v = lim.accel_v_mps2 * dt
        dvz = min(max(dvz, -max_v), max_v)
        self.a_d = [dvx / dt, dvy / dt, dvz / dt]
        self.v_d = [self.v_d[0] + dvx, self.v_d[1] + dvy, self.v_d[2] + dvz]
        self.p_d = [self.p_d[i] + self.v_d[i] * dt for i in range(3)]

    def tracking_acceleration(self, dt: float) -> list[float]:
        """Commanded acceleration NED: feed-forward + P on velocity (with position correction) + I.

        Horizontal part limited by the tilt limit, vertical part by the thrust range.
        """
        lim = self.limits
        a = [0.0, 0.0, 0.0]
        for i in range(3):
            v_c = self.v_d[i] + lim.pos_gain_per_s * (self.p_d[i] - self.p[i] - self.err_p[i])
            err = v_c - self.v[i] - self.err_v[i]
            self.integ[i] = min(max(self.integ[i] + lim.vel_int_gain_per_s2 * err * dt, -lim.int_limit_mps2), lim.int_limit_mps2)
            a[i] = self.a_d[i] + lim.vel_gain_per_s * err + self.integ[i]
        a_h_max = GRAVITY_MPS2 * math.tan(lim.tilt_max_rad)
        ah = math.hypot(a[0], a[1])
        if ah > a_h_max:
            a[0] *= a_h_max / ah
            a[1] *= a_h_max / ah
        # thrust between 10 % and thrust_max_g of the weight: a_z in [-(T-1) g, 0.9 g]
        a[2] = min(max(a[2], -(lim.thrust_max_g - 1.0) * GRAVITY_MPS2), 0.9 * GRAVITY_MPS2)
        return a

    def update_yaw(self, sp: Setpoint, dt: float) -> None:
        max_step = self.limits.yaw_rate_max_rps * dt
        if _finite(sp.yaw_rate_rps):
            self.yaw = wrap_pi(self.yaw + min(max(sp.yaw_rate_rps * dt, -max_step), max_step))
            return
        target = sp.yaw_rad
        if not _finite(target) and sp.yaw_follows_velocity and math.hypot(self.v_d[0], self.v_d[1]) > 1.0:
            target = math.atan2(self.v_d[1], self.v_d[0])
        if _finite(target):
            self.yaw = wrap_pi(self.yaw + min(max(wrap_pi(target - self.yaw), -max_step), max_step))

    # ---- plant -----------------------------------------------------------------------------

    def step(self, dt: float, sp: Setpoint, wind_ned_mps=(0.0, 0.0, 0.0), armed: bool = True) -> None:
        """Advance the truth by ``dt`` seconds under setpoint ``sp`` (ignored when disarmed)."""
        self.last_dt = dt
        self.prev_thrust = list(self.thrust)
        self.prev_yaw = self.yaw
        lim = self.limits
        if not armed:
            self.thrust = [0.0, 0.0, 0.0]
            if self.landed:
                self.v = [0.0, 0.0, 0.0]
                self.accel = [0.0, 0.0, 0.0]
                self.thrust = [0.0, 0.0, -GRAVITY_MPS2]  # resting on the ground: the ground carries it
                self.reset_reference()
                return
            a_cmd = [0.0, 0.0, GRAVITY_MPS2]  # motors off in the air: it falls
            self.reset_reference()
        else:
            vt = self.target_velocity(sp)
            if self.landed and vt[2] > -0.05:
                # on the ground and not asked to climb: stay put, keep the reference on the vehicle
                self.reset_reference()
                self.update_yaw(sp, dt)
                self.thrust = [0.0, 0.0, -GRAVITY_MPS2]
                self.v = [0.0, 0.0, 0.0]
                self.accel = [0.0, 0.0, 0.0]
                return
            self.shape_reference(vt, dt)
            a_cmd = self.tracking_acceleration(dt)
            self.update_yaw(sp, dt)
        # thrust specific force (without gravity) follows the command through the attitude lag
        target_thrust = [a_cmd[0], a_cmd[1], a_cmd[2] - GRAVITY_MPS2] if armed else [0.0, 0.0, 0.0]
        k = min(1.0, dt / lim.attitude_tau_s)
        self.thrust = [self.thrust[i] + k * (target_thrust[i] - self.thrust[i]) for i in range(3)]
        w = wind_ned_mps
        acc = [self.thrust[0] + lim.drag_per_s * (w[0] - self.v[0]),
               self.thrust[1] + lim.drag_per_s * (w[1] - self.v[1]),
               self.thrust[2] + GRAVITY_MPS2 + lim.drag_per_s * (w[2] - self.v[2])]
        v_new = [self.v[i] + acc[i] * dt for i in range(3)]
        p_new = [self.p[i] + 0.5 * (self.v[i] + v_new[i]) * dt for i in range(3)]
        self.landed = False
        if p_new[2] >= self.ground_down_m:
            # touchdown (or resting): the ground stops the fall and friction the slide
            p_new[2] = self.ground_down_m
            if v_new[2] >= 0.0:
                v_new = [0.0, 0.0, 0.0]
                self.landed = True
        self.accel = [(v_new[i] - self.v[i]) / dt for i in range(3)]
        self.p, self.v = p_new, v_new
        if self.landed:
            self.reset_reference()

    # ---- outputs ---------------------------------------------------------------------------

    @staticmethod
    def _rotation(thrust: list[float], yaw: float) -> np.ndarray:
        """Body->NED rotation with body z along -thrust and the nose as close to ``yaw`` as tilt allows.

        Plain floats: this runs for every attitude-bearing message (np.cross costs ~20 us a call).
        """
        n = math.sqrt(thrust[0] ** 2 + thrust[1] ** 2 + thrust[2] ** 2)
        zx, zy, zz = (-thrust[0] / n, -thrust[1] / n, -thrust[2] / n) if n > 1e-6 else (0.0, 0.0, 1.0)
        cx, cy = math.cos(yaw), math.sin(yaw)
        # y_b = z_b x x_c (x_c = heading direction, horizontal), normalised; x_b = y_b x z_b
        yx, yy, yz = -zz * cy, zz * cx, zx * cy - zy * cx
        m = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / m, yy / m, yz / m
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx
        return np.array([[xx, yx, zx], [xy, yy, zy], [xz, yz, zz]])

    def rotation_body_to_ned(self) -> np.ndarray:
        """(3, 3) true attitude R_nb."""
        return self._rotation(self.thrust, self.yaw)

    def quaternion_wxyz(self) -> np.ndarray:
        """(4,) true attitude body->NED, Hamilton, scalar first."""
        return matrix_to_quat(self.rotation_body_to_ned())

    def angular_velocity_body(self) -> np.ndarray:
        """(3,) body rates (rad/s) from the change of attitude over the last step."""
        R0 = self._rotation(self.prev_thrust, self.prev_yaw)
        R1 = self.rotation_body_to_ned()
        dR = R0.T @ R1
        # small-angle vee of the skew part: omega dt ~ vee((dR - dR^T) / 2)
        w = 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]])
        return w / max(self.last_dt, 1e-9)

    def specific_force_body(self) -> np.ndarray:
        """(3,) accelerometer reading (m/s^2, body FRD): acceleration minus gravity."""
        f_ned = np.asarray(self.accel) - np.array([0.0, 0.0, GRAVITY_MPS2])
        return self.rotation_body_to_ned().T @ f_ned


@dataclass(slots=True)
class WindModel:
    """Steady wind plus horizontal gusts, each gust axis a first-order Gauss-Markov process.

    ``step(dt)`` draws from ``rng`` (seeded), so the wind history is reproducible.
    """

    mean_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_sigma_mps: float = 0.0
    gust_tau_s: float = 3.0
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    gust: list[float] = field(default_factory=lambda: [0.0, 0.0])

    def __post_init__(self) -> None:
        if len(self.mean_ned_mps) != 3 or not all(_finite(float(x)) for x in self.mean_ned_mps):
            raise ValueError(f"wind must be 3 finite numbers (north, east, down), got {self.mean_ned_mps!r}")
        if self.gust_sigma_mps > 0:
            self.gust = list(self.rng.normal(0.0, self.gust_sigma_mps, 2))

    def step(self, dt: float) -> None:
        if self.gust_sigma_mps <= 0:
            return
        phi = math.exp(-dt / self.gust_tau_s)
        w = self.rng.normal(0.0, 1.0, 2)
        s = self.gust_sigma_mps * math.sqrt(1.0 - phi * phi)
        self.gust = [phi * self.gust[0] + s * w[0], phi * self.gust[1] + s * w[1]]

    def velocity_ned(self) -> tuple[float, float, float]:
        m = self.mean_ned_mps
        return (m[0] + self.gust[0], m[1] + self.gust[1], m[2])
