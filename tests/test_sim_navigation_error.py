"""The simulated navigation error's statistics against its model (docs/sim.md, "Navigation error").

The ``ekf`` model: per component a slow critically damped Gauss-Markov part (autocorrelation
``(1 + w t) exp(-w t)``, ``w = 2 / tau``) plus a white part. Each check's tolerance comes from the
sampling error of the statistic over the series (stated at each assert), not from the eye.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.config import SimConfig, replace
from drivers.sim.navigation_error import ATT, POS, VEL, GaussMarkovNavError, NavErrorSpec

STEP_S = 0.1          # the error is stepped at 10 Hz here (the simulator: sim.nav_rate_hz)
DURATION_S = 7200.0   # two hours: 120 correlation times of the 60 s position error


@pytest.fixture(scope="module")
def ekf_series():
    spec = NavErrorSpec.from_config(SimConfig())
    assert SimConfig().nav_error_model == "ekf"
    g = GaussMarkovNavError(spec, np.random.default_rng(2024))
    out = np.empty((int(DURATION_S / STEP_S), 9))
    for k in range(len(out)):
        g.step(STEP_S)
        out[k] = g.e
    return spec, out


def _acf_model(w: float, lag_s: float) -> float:
    return (1.0 + w * lag_s) * math.exp(-w * lag_s)


def test_each_component_has_its_stated_sigma_within_its_sampling_error(ekf_series):
    spec, e = ekf_series
    sigma = np.asarray(spec.sigma)
    slow, white = spec.slow_sigma, np.asarray(spec.white)
    omega = np.concatenate([spec.pos_vel_omega, spec.pos_vel_omega, spec.attitude_omega])
    for i in range(9):
        if sigma[i] == 0:
            continue
        # variance of a sample variance over T of a process whose autocorrelation is rho:
        # 2 sigma^4 (int rho^2 dt) / T; for (1 + w t) e^(-w t), int over the real line = 5 / (2 w).
        frac = slow[i] ** 2 / sigma[i] ** 2
        rel_sd_var = math.sqrt(2.0 * (frac ** 2 * 5.0 / (2.0 * omega[i]) + STEP_S) / DURATION_S)
        measured = e[:, i].std()
        assert abs(measured ** 2 / sigma[i] ** 2 - 1.0) < 4.0 * rel_sd_var, (i, measured, sigma[i], rel_sd_var)
    assert np.all(white <= sigma)


def test_frame_to_frame_changes_are_the_white_part_plus_the_slow_drift(ekf_series):
    spec, e = ekf_series
    slow, white = spec.slow_sigma, np.asarray(spec.white)
    omega = np.concatenate([spec.pos_vel_omega, spec.pos_vel_omega, spec.attitude_omega])
    d = np.diff(e, axis=0)
    # E[d^2] = 2 w^2 + 2 sigma_slow^2 (1 - rho(dt)); nearly independent increments: rel. sd of the mean
    # square ~ sqrt(2 / N) (0.5 % here): 3 % is six of them.
    expected = np.sqrt(2.0 * white ** 2 + 2.0 * slow ** 2 * (1.0 - np.array([_acf_model(w, STEP_S) for w in omega])))
    measured = np.sqrt(np.mean(d * d, axis=0))
    for i in range(9):
        if expected[i] > 0:
            assert measured[i] == pytest.approx(expected[i], rel=0.03), (i, measured[i], expected[i])
    # an EKF's attitude error wanders slowly: under a tenth of a degree from one 15 Hz frame to the next
    frame = e[::1][:: max(1, round(1 / 15 / STEP_S))]
    assert np.degrees(np.sqrt(np.mean(np.diff(frame[:, ATT], axis=0) ** 2, axis=0))).max() < 0.1


def test_the_slow_part_is_correlated_over_its_correlation_time(ekf_series):
    spec, e = ekf_series
    sigma, slow = np.asarray(spec.sigma), spec.slow_sigma
    for comp, w in ((POS, spec.pos_vel_omega), (ATT, spec.attitude_omega)):
        for axis in range(3):
            i = comp.start + axis
            for lag_s in (10.0, 30.0, 60.0):
                k = int(lag_s / STEP_S)
                x = e[:, i] - e[:, i].mean()
                measured = float(np.mean(x[:-k] * x[k:]) / np.mean(x * x))
                expected = slow[i] ** 2 / sigma[i] ** 2 * _acf_model(w[axis], lag_s)
                # sampling error of an autocorrelation estimate ~ sqrt(int rho^2 / T) = sqrt(5 / (2 w T))
                tol = 4.0 * math.sqrt(5.0 / (2.0 * w[axis] * DURATION_S))
                assert abs(measured - expected) < tol, (i, lag_s, measured, expected, tol)


def test_the_velocity_error_is_the_rate_of_the_slow_position_error_plus_white_noise(ekf_series):
    spec, _ = ekf_series
    s = SimConfig()
    assert np.allclose(spec.slow_sigma[VEL], (2.0 / s.nav_pos_tau_h_s) * spec.slow_sigma[POS], rtol=0, atol=1e-12) or \
        spec.pos_tau_s[2] != s.nav_pos_tau_h_s
    assert np.allclose(np.asarray(spec.sigma)[VEL] ** 2, spec.slow_sigma[VEL] ** 2 + np.asarray(spec.white)[VEL] ** 2)


def test_the_harsh_model_has_no_white_part_and_no_error_means_none():
    harsh = NavErrorSpec.from_config(replace(SimConfig(), nav_error_model="harsh"))
    assert harsh.white == (0.0,) * 9 and harsh.pos_tau_s is None
    assert np.array_equal(harsh.slow_sigma, np.asarray(harsh.sigma))
    zero = replace(SimConfig(), nav_pos_sigma_h_m=0.0, nav_pos_sigma_v_m=0.0, nav_vel_sigma_mps=0.0,
                   nav_tilt_sigma_deg=0.0, nav_yaw_sigma_deg=0.0)
    g = GaussMarkovNavError(NavErrorSpec.from_config(zero), np.random.default_rng(1))
    g.step(0.02)
    assert np.abs(g.e).max() < 1e-6  # (the discretisation keeps a 1e-18 jitter for a real Cholesky factor)
