"""EKF-like navigation error whose reported covariance is exactly the injected error statistics.

A real autopilot's estimate is truth plus a slowly wandering error, and its filter reports a
covariance for it. The simulator reverses that: it injects an error with *known* statistics and
reports those statistics, so a consumer that trusts the reported covariance is right to.

Position and velocity, per axis: one critically damped second-order Gauss-Markov process, the
velocity error being the rate of the position error (an EKF's position error is the integral of
its velocity error; two independent errors would make the vehicle's controller fight a position
estimate that moves without its velocity estimate saying so):

    d e_p = e_v dt,   d e_v = (-w^2 e_p - 2 w e_v) dt + q dW,   w = sigma_v / sigma_p,
    q^2 = 4 w sigma_v^2   ->   stationary Var(e_p) = sigma_p^2, Var(e_v) = sigma_v^2, Cov = 0.

It is discretised exactly for any step (``F = exp(A dt)``, ``Q = P - F P F^T`` with ``P`` the
stationary covariance) and started from its stationary law, so its marginal covariance is
``diag(sigma^2)`` at every instant, not only asymptotically.

Attitude (rotation vector in NED, ``R_true = Exp(e_att) R_est`` as in
companion.method.messages.NavState): per axis the same critically damped second-order process as
position/velocity, with the attitude error's rate as its hidden second state and
``w = 2 / tau`` (``tau`` = ``att_tau_s``, the integral correlation time: the autocorrelation
``(1 + w t) exp(-w t)`` integrates to ``2 / w``). A real EKF's attitude error is smooth: it is the
integral of a gyro bias error, corrected a little at each fusion, so it wanders over seconds and
does not jump from one camera frame to the next. A first-order (Ornstein-Uhlenbeck) process with
the same sigma and tau changes by ``sigma sqrt(2 dt / tau)`` per step, a random walk at small
scales: 0.23 deg of yaw between two frames at 15 Hz for the default 2 deg and 10 s, which a
camera mapper sees as image motion no real vehicle has. This one changes by about
``sigma w dt`` (0.03 deg). Equal roll and pitch sigmas make the roll/pitch/yaw variances PX4
reports the same numbers to first order whatever the heading.

What is reported (PX4's ODOMETRY diagonal, ESTIMATOR_STATUS accuracies; ArduPilot's GPS_RAW_INT
accuracies) is ``diag(sigma^2)``, so the normalised estimation error squared ``e^T P^-1 e`` is
chi-square with 9 degrees of freedom at every sample (consecutive samples are correlated).

The simulated GPS receiver measures truth plus the position error plus white noise: the
estimate follows GPS, so the GPS error and the estimate error are mostly the same slow error, and
the EKF innovations (GPS minus estimate) are the white part. Test ratios follow EKF3's form
``|innovation|^2 / (gate^2 * innovation variance)`` (AP_NavEKF3_PosVelFusion.cpp).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.method.geometry import so3_exp

POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)


@dataclass(frozen=True, slots=True)
class NavErrorSpec:
    """Stationary sigmas of the 9 error components and the attitude correlation times.

    sigma: (9,) [pos N, E, D (m), vel N, E, D (m/s), att N, E, D (rad)]: the total sigma of each
    component, slow and fast parts together (what the vehicle reports).
    att_tau_s: (3,) seconds, the integral correlation time of each attitude axis (its process
    has ``w = 2 / tau``).
    pos_tau_s: (3,) seconds, the integral correlation time of each position axis (``w = 2 / tau``);
    None (the ``harsh`` model) = from the sigmas, ``w = sigma_v / sigma_p``.
    white: (9,) sigma of the fast part of each component, white from one navigation step to the
    next (the ``ekf`` model; zeros in the ``harsh`` one). The slow part carries the rest of the
    variance: ``sigma_slow^2 = sigma^2 - white^2``; for velocity the slow part is the rate of the
    slow position error (``w sigma_p_slow``) and the white part makes up the total.
    """

    sigma: tuple[float, ...]
    att_tau_s: tuple[float, float, float] = (10.0, 10.0, 10.0)
    pos_tau_s: tuple[float, float, float] | None = None
    white: tuple[float, ...] = (0.0,) * 9

    def __post_init__(self) -> None:
        if len(self.sigma) != 9 or len(self.att_tau_s) != 3:
            raise ValueError(f"NavErrorSpec needs 9 sigmas and 3 attitude correlation times, got {len(self.sigma)} and {len(self.att_tau_s)}")
        for i, s in enumerate(self.sigma):
            if not (math.isfinite(s) and s >= 0):
                raise ValueError(f"NavErrorSpec.sigma[{i}] must be finite and >= 0, got {s!r}")
        for i, t in enumerate(self.att_tau_s):
            if not (math.isfinite(t) and t > 0):
                raise ValueError(f"NavErrorSpec.att_tau_s[{i}] must be finite and > 0, got {t!r}")
        if len(self.white) != 9 or any(not (math.isfinite(w) and 0 <= w <= s) for w, s in zip(self.white, self.sigma)):
            raise ValueError(f"NavErrorSpec.white must be 9 values within 0..sigma, got {self.white!r}")
        if self.pos_tau_s is not None and (len(self.pos_tau_s) != 3 or
                                           any(not (math.isfinite(t) and t > 0) for t in self.pos_tau_s)):
            raise ValueError(f"NavErrorSpec.pos_tau_s must be 3 finite times > 0, got {self.pos_tau_s!r}")
        for i in range(3):
            if self.sigma[3 + i] > 0 and self.sigma[i] == 0:
                raise ValueError(f"NavErrorSpec: velocity sigma[{3 + i}] > 0 needs a position sigma[{i}] > 0 "
                                 "(the velocity error is the rate of the position error)")

    @classmethod
    def from_config(cls, sim) -> "NavErrorSpec":
        """From a :class:`companion.config.SimConfig`."""
        h, v, vel = sim.nav_pos_sigma_h_m, sim.nav_pos_sigma_v_m, sim.nav_vel_sigma_mps
        tilt, yaw = math.radians(sim.nav_tilt_sigma_deg), math.radians(sim.nav_yaw_sigma_deg)
        sigma = (h, h, v, vel, vel, vel, tilt, tilt, yaw)
        if getattr(sim, "nav_error_model", "harsh") == "harsh":
            return cls(sigma=sigma, att_tau_s=(sim.nav_att_tau_s,) * 3)
        tau_p = (sim.nav_pos_tau_h_s, sim.nav_pos_tau_h_s, sim.nav_pos_tau_v_s)
        wp, wv = sim.nav_pos_white_m, sim.nav_vel_white_mps
        wt, wy = math.radians(sim.nav_tilt_white_deg), math.radians(sim.nav_yaw_white_deg)
        w_pos = tuple(min(wp, s) for s in (h, h, v))
        # velocity: the rate of the slow position error plus its own white part (nav_vel_sigma_mps is
        # the harsh model's; here the velocity sigma follows from the position's and is what is reported)
        v_slow = tuple((2.0 / t) * math.sqrt(s * s - w * w) for s, w, t in zip((h, h, v), w_pos, tau_p))
        w_vel = tuple(wv if s > 0 else 0.0 for s in (h, h, v))  # no position error: no velocity error either
        sigma = (h, h, v, *(math.hypot(vs, w) for vs, w in zip(v_slow, w_vel)), tilt, tilt, yaw)
        white = (*w_pos, *w_vel, min(wt, tilt), min(wt, tilt), min(wy, yaw))
        return cls(sigma=sigma, att_tau_s=(sim.nav_att_tau_ekf_s,) * 3, pos_tau_s=tau_p, white=white)

    @property
    def covariance(self) -> np.ndarray:
        """(9, 9) the stationary covariance diag(sigma^2): what the vehicle reports."""
        return np.diag(np.square(self.sigma))

    @property
    def slow_sigma(self) -> np.ndarray:
        """(9,) sigma of the slow part of each component: ``sqrt(sigma^2 - white^2)``; for velocity,
        with ``pos_tau_s``, the rate of the slow position error ``w sigma_p_slow``."""
        s, w = np.asarray(self.sigma, float), np.asarray(self.white, float)
        slow = np.where(w > 0, np.sqrt(np.maximum(s * s - w * w, 0.0)), s)
        if self.pos_tau_s is not None:
            slow[VEL] = self.pos_vel_omega * slow[POS]
        return slow

    @property
    def pos_vel_omega(self) -> np.ndarray:
        """(3,) natural frequency of each axis' position/velocity process (0 = frozen): ``2 / tau``
        with ``pos_tau_s``, else ``sigma_v / sigma_p``."""
        s = np.asarray(self.sigma)
        if self.pos_tau_s is not None:
            return np.where(s[POS] > 0, 2.0 / np.asarray(self.pos_tau_s, float), 0.0)
        return np.divide(s[VEL], s[POS], out=np.zeros(3), where=s[POS] > 0)

    @property
    def attitude_omega(self) -> np.ndarray:
        """(3,) natural frequency ``w = 2 / tau`` of each attitude axis' critically damped process."""
        return 2.0 / np.asarray(self.att_tau_s, float)


def critically_damped_transition(omega: np.ndarray, dt: float) -> np.ndarray:
    """exp(A dt) for A = [[0, 1], [-w^2, -2w]]: (3,) omegas -> (3, 2, 2)."""
    w = np.asarray(omega, float)
    e = np.exp(-w * dt)
    F = np.empty(w.shape + (2, 2))
    F[..., 0, 0] = e * (1 + w * dt)
    F[..., 0, 1] = e * dt
    F[..., 1, 0] = -e * w * w * dt
    F[..., 1, 1] = e * (1 - w * dt)
    return F


def stationary_discretisation(omega: np.ndarray, sigma: np.ndarray, sigma_rate: np.ndarray,
                              dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(F, chol(Q)), each (3, 2, 2), of three critically damped processes [e, de/dt] whose stationary
    covariance is ``diag(sigma^2, sigma_rate^2)`` (``sigma_rate = w sigma``): ``Q = P - F P F^T``."""
    F = critically_damped_transition(omega, dt)
    P = np.zeros((3, 2, 2))
    P[:, 0, 0] = np.square(sigma)
    P[:, 1, 1] = np.square(sigma_rate)
    Q = P - F @ P @ np.swapaxes(F, -1, -2)
    Q = 0.5 * (Q + np.swapaxes(Q, -1, -2))
    # Q is PSD; a tiny jitter keeps the Cholesky factor real where a sigma is zero
    return F, np.linalg.cholesky(Q + 1e-18 * np.eye(2))


class GaussMarkovNavError:
    """The injected error e (9,), advanced with ``step(dt)``; exact discretisation for any dt.

    ``attitude_rate_error`` (3,) is the hidden second state of the attitude process (rad/s)."""

    def __init__(self, spec: NavErrorSpec, rng: np.random.Generator):
        self.spec = spec
        self.rng = rng
        self._sigma = spec.slow_sigma  # of the slow processes
        self._white = np.asarray(spec.white, float)
        self._has_white = bool(np.any(self._white > 0))
        self._tau = np.asarray(spec.att_tau_s, float)
        self._omega = spec.pos_vel_omega
        self._att_omega = spec.attitude_omega
        self._att_rate_sigma = self._att_omega * self._sigma[ATT]
        self._cache: tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self.slow = self._sigma * rng.standard_normal(9)
        self.attitude_rate_error = self._att_rate_sigma * rng.standard_normal(3)
        self.e = self.slow + (self._white * rng.standard_normal(9) if self._has_white else 0.0)

    def _discrete(self, dt: float):
        """(F, chol(Q)) of position/velocity and of attitude/attitude rate, each (3, 2, 2), for
        this dt (cached: dt is usually fixed)."""
        if self._cache is None or self._cache[0] != dt:
            F, L = stationary_discretisation(self._omega, self._sigma[POS], self._sigma[VEL], dt)
            Fa, La = stationary_discretisation(self._att_omega, self._sigma[ATT], self._att_rate_sigma, dt)
            self._cache = (dt, F, L, Fa, La)
        return self._cache[1:]

    def step(self, dt: float) -> None:
        if not dt > 0:
            raise ValueError(f"GaussMarkovNavError.step needs dt > 0, got {dt!r}")
        F, L, Fa, La = self._discrete(dt)
        w = self.rng.standard_normal(12)
        slow = self.slow
        pv = np.stack([slow[POS], slow[VEL]], axis=-1)  # (3, 2): per axis [e_p, e_v]
        pv = (F @ pv[..., None])[..., 0] + (L @ w[:6].reshape(3, 2)[..., None])[..., 0]
        slow[POS], slow[VEL] = pv[:, 0], pv[:, 1]
        ar = np.stack([slow[ATT], self.attitude_rate_error], axis=-1)  # (3, 2): per axis [e_att, rate]
        ar = (Fa @ ar[..., None])[..., 0] + (La @ w[6:].reshape(3, 2)[..., None])[..., 0]
        slow[ATT], self.attitude_rate_error = ar[:, 0], ar[:, 1]
        # the fast part: white from one step to the next (the ``harsh`` model has none: e is the slow part)
        self.e = slow + self._white * self.rng.standard_normal(9) if self._has_white else slow.copy()

    @property
    def position_error_m(self) -> np.ndarray:
        return self.e[POS]

    @property
    def velocity_error_mps(self) -> np.ndarray:
        return self.e[VEL]

    @property
    def attitude_error_rad(self) -> np.ndarray:
        return self.e[ATT]

    def estimated_rotation(self, R_true: np.ndarray) -> np.ndarray:
        """R_est with R_true = Exp(e_att) R_est, i.e. R_est = Exp(-e_att) R_true. (3, 3)."""
        return so3_exp(-self.e[ATT]) @ R_true


def normalised_error_squared(error: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """NEES ``e^T P^-1 e``: error (..., k), covariance (k, k) or (..., k, k) -> (...)."""
    error = np.asarray(error, float)
    solved = np.linalg.solve(covariance, error[..., None])[..., 0]
    return np.sum(error * solved, axis=-1)


def innovation_test_ratio(innovation: np.ndarray, innovation_variance: np.ndarray, gate_sigma: float) -> float:
    """EKF3-style consistency test ratio ``sum(innov^2) / (gate^2 * sum(var))``; < 1 passes the gate.

    innovation, innovation_variance: (k,) for the axes fused together (e.g. north and east).
    """
    innovation = np.asarray(innovation, float)
    var = float(np.sum(innovation_variance))
    if not var > 0:
        return 0.0
    return float(np.sum(innovation * innovation) / (gate_sigma * gate_sigma * var))


@dataclass(slots=True)
class GpsFix:
    """One simulated GPS solution: position/velocity error about truth and its 1-sigma accuracies."""

    position_error_m: np.ndarray  # (3,) NED error of the fix about truth
    velocity_error_mps: np.ndarray  # (3,)
    h_acc_m: float
    v_acc_m: float
    vel_acc_mps: float
    innovation_pos_m: np.ndarray  # (3,) fix minus navigation estimate
    innovation_vel_mps: np.ndarray  # (3,)


class GpsReceiver:
    """GPS = truth + navigation position error + white noise; reports accuracies from the same sigmas."""

    def __init__(self, nav: GaussMarkovNavError, noise_m: float, vel_noise_mps: float, rng: np.random.Generator):
        if not (math.isfinite(noise_m) and noise_m >= 0 and math.isfinite(vel_noise_mps) and vel_noise_mps >= 0):
            raise ValueError(f"GPS noise must be finite and >= 0, got {noise_m!r}, {vel_noise_mps!r}")
        self.nav = nav
        self.noise_m = noise_m
        self.vel_noise_mps = vel_noise_mps
        self.rng = rng
        self.fix = self.sample()

    def sample(self) -> GpsFix:
        """Draw a new fix (call at the receiver rate)."""
        s = np.asarray(self.nav.spec.sigma)
        white_p = self.noise_m * self.rng.standard_normal(3)
        white_v = self.vel_noise_mps * self.rng.standard_normal(3)
        self.fix = GpsFix(
            position_error_m=self.nav.position_error_m + white_p,
            velocity_error_mps=self.nav.velocity_error_mps + white_v,
            # the fix's own 1-sigma: the slow error plus the white noise, per axis
            h_acc_m=float(math.hypot(s[0], self.noise_m)),
            v_acc_m=float(math.hypot(s[2], self.noise_m)),
            vel_acc_mps=float(math.hypot(s[3], self.vel_noise_mps)),
            innovation_pos_m=white_p,
            innovation_vel_mps=white_v,
        )
        return self.fix

    def test_ratios(self, gate_sigma: float = 5.0) -> tuple[float, float, float]:
        """(velocity, horizontal position, vertical position) innovation test ratios.

        The innovation variance is measurement noise plus the estimate's variance (R + H P H^T).
        Gate 5 sigma = EKF3's default VEL_I_GATE / POS_I_GATE / HGT_I_GATE of 500 (centi-sigma).
        """
        s = np.asarray(self.nav.spec.sigma)
        fix = self.fix
        var_p = self.noise_m ** 2 + s[POS] ** 2
        var_v = self.vel_noise_mps ** 2 + s[VEL] ** 2
        vel = innovation_test_ratio(fix.innovation_vel_mps, var_v, gate_sigma)
        pos_h = innovation_test_ratio(fix.innovation_pos_m[:2], var_p[:2], gate_sigma)
        pos_v = innovation_test_ratio(fix.innovation_pos_m[2:], var_p[2:], gate_sigma)
        return vel, pos_h, pos_v
