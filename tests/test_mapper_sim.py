"""Feature-level simulation of the mapper (seed 000, section IV, scaled to metres).

A camera pitched 45 deg down on a vehicle flying north at 6 m/s, 15 m above flat ground, towards
a 12 m block. Known 3D points (ground and the block's top and front face, with occlusion by the
block) are projected with the *true* pose, given 1 px noise, and handed to the mapper together
with a navigation state whose errors are drawn from the very P_x the mapper is told. Every run
is played through both parameterisations with identical measurements and navigation.

Run ``python tests/test_mapper_sim.py`` (or pytest with ``-s``) to print the figures.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from companion.config import MapperConfig
from companion.geometry import CameraMount, PinholeCamera, euler_to_matrix, matrix_to_quat, so3_exp
from companion.mapper import Mapper
from companion.messages import NavState

CAMERA = PinholeCamera(fx=625.3, fy=625.3, cx=319.5, cy=239.5, width=640, height=480)  # 42 deg vertical FOV
MOUNT = CameraMount.from_euler_deg(0.0, -45.0, 0.0, offset_m=(0.4, 0.0, 0.15))
ALTITUDE_M = 15.0
SPEED_MPS = 6.0
RATE_HZ = 16.0  # the paper's frame rate
N_FRAMES = 150
SIGMA_POS_M = 0.1
SIGMA_ATT_RAD = np.radians(0.2)
PIXEL_SIGMA = 1.0
BLOCK_MIN = np.array([45.0, -6.0, -12.0])  # NED box: x 45..53 north, y -6..6 east, 12 m tall
BLOCK_MAX = np.array([53.0, 6.0, 0.0])
N_RUNS = 24
GROUND_SPACING_M = 4.0


# ----------------------------------------------------------------------------------------------
# World and trajectory
# ----------------------------------------------------------------------------------------------


def make_world(rng: np.random.Generator) -> np.ndarray:
    """Ground points on a jittered 2.5 m grid plus points on the block's top and front face. (N, 3)."""
    gx, gy = np.meshgrid(np.arange(0.0, 100.0, GROUND_SPACING_M), np.arange(-30.0, 30.01, GROUND_SPACING_M), indexing="ij")
    ground = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    ground[:, :2] += rng.uniform(-0.3, 0.3, (len(ground), 2)) * GROUND_SPACING_M
    inside = np.all((ground[:, :2] >= BLOCK_MIN[:2]) & (ground[:, :2] <= BLOCK_MAX[:2]), axis=1)
    ground = ground[~inside]
    # Block texture at random places (a regular pattern along the flight line aliases any matcher).
    n_top, n_front = 24, 24
    top = np.column_stack([rng.uniform(45.3, 52.7, n_top), rng.uniform(-5.7, 5.7, n_top), np.full(n_top, -12.0)])
    front = np.column_stack([np.full(n_front, 45.0), rng.uniform(-5.7, 5.7, n_front), rng.uniform(-11.7, -0.3, n_front)])
    block = np.vstack([top, front])
    return np.vstack([ground, block])


def occluded(origin: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (N, 3) hidden from ``origin`` by the block (slab test on the open segment). (N,) bool."""
    d = points - origin
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (BLOCK_MIN - origin) / d
        t2 = (BLOCK_MAX - origin) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=1)
    return (t_near < t_far) & (t_far > 1e-6) & (t_near < 1.0 - 1e-6)


def true_pose(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Body position (3,) and R_nb (3, 3) at frame k: straight and level north with a gentle wobble."""
    t = k / RATE_HZ
    p = np.array([SPEED_MPS * t, 0.3 * np.sin(0.7 * t), -ALTITUDE_M + 0.2 * np.sin(0.5 * t)])
    R = euler_to_matrix(np.radians(2.0) * np.sin(1.3 * t), np.radians(1.5) * np.sin(0.9 * t), np.radians(1.0) * np.sin(0.4 * t))
    return p, R


def navigation_covariance() -> np.ndarray:
    cov = np.zeros((9, 9))
    cov[0:3, 0:3] = np.eye(3) * SIGMA_POS_M**2
    cov[3:6, 3:6] = np.eye(3) * 0.1**2
    cov[6:9, 6:9] = np.eye(3) * SIGMA_ATT_RAD**2
    return cov


def make_run(seed: int):
    """Measurements and navigation for one run: lists of (NavState, uv (M, 2), point index (M,),
    true camera centre (3,))."""
    rng = np.random.default_rng(seed)
    world = make_world(rng)
    score = rng.permutation(len(world))  # a fixed "corner strength" per point: lower = stronger
    cov = navigation_covariance()
    frames = []
    for k in range(N_FRAMES):
        p, R_nb = true_pose(k)
        p_c, R_nc = MOUNT.camera_pose(p, R_nb)
        h_c = (world - p_c) @ R_nc
        uv = CAMERA.project(h_c)
        seen = CAMERA.in_image(uv) & ~occluded(p_c, world)
        idx = np.flatnonzero(seen)
        idx = idx[np.argsort(score[idx])][:100]
        z = uv[idx] + rng.normal(0.0, PIXEL_SIGMA, (len(idx), 2))
        # Estimate = truth with an error drawn from P_x: p_est = p + dp, R_true = Exp(dtheta) R_est.
        p_est = p + rng.normal(0.0, SIGMA_POS_M, 3)
        R_est = so3_exp(-rng.normal(0.0, SIGMA_ATT_RAD, 3)) @ R_nb
        nav = NavState(k / RATE_HZ, p_est, np.array([SPEED_MPS, 0, 0]), matrix_to_quat(R_est), cov)
        frames.append((nav, z, idx, p_c))
    return world, frames


# ----------------------------------------------------------------------------------------------
# Play a run through a mapper and score it against the truth
# ----------------------------------------------------------------------------------------------


def play(world, frames, parameterisation: str, **overrides) -> dict:
    cfg = dataclasses.replace(MapperConfig(), parameterisation=parameterisation, pixel_sigma_px=PIXEL_SIGMA, **overrides)
    mapper = Mapper(cfg, CAMERA, MOUNT, default_ground_alt_m=0.0)
    truth_of: dict[int, int] = {}
    born: dict[int, int] = {}
    origin: dict[int, np.ndarray] = {}
    first_converged: dict[int, int] = {}
    final: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    n_matched = n_wrong = 0
    misassociated: set[int] = set()
    for k, (nav, z, idx, p_c_true) in enumerate(frames):
        step = mapper.step_measurements(nav, z)
        assert step.rejected_reason == ""
        for fid, m in zip(step.matched_ids, step.matched_measurements):
            n_matched += 1
            if truth_of[int(fid)] != idx[m]:
                n_wrong += 1
                misassociated.add(int(fid))
        for fid, m in zip(step.initialised_ids, step.initialised_measurements):
            truth_of[int(fid)] = int(idx[m])
            born[int(fid)] = k
            origin[int(fid)] = p_c_true
        for fid, X, P in zip(step.points.feature_ids, step.points.positions_ned_m, step.points.covariances):
            first_converged.setdefault(int(fid), k)
            final[int(fid)] = (X, P)
    snap = mapper.features()
    for fid, X, P, conv in zip(snap.ids, snap.positions_ned_m, snap.covariances, snap.converged):
        if conv:
            final[int(fid)] = (X, P)
    frames_to_converge = np.array([first_converged[f] - born[f] for f in first_converged])
    ids = sorted(final)
    err = np.array([final[f][0] - world[truth_of[f]] for f in ids]).reshape(-1, 3)
    cov = np.array([final[f][1] for f in ids]).reshape(-1, 3, 3)
    nees = np.einsum("ni,nij,nj->n", err, np.linalg.inv(cov), err) if len(ids) else np.zeros(0)
    depth_err = np.array(
        [
            abs(np.linalg.norm(final[f][0] - origin[f]) - np.linalg.norm(world[truth_of[f]] - origin[f]))
            for f in ids
        ]
    )
    on_block = np.array([world[truth_of[f]][2] < -0.5 for f in ids], dtype=bool)
    clean = np.array([f not in misassociated for f in ids], dtype=bool)
    return {
        "frames_to_converge": frames_to_converge,
        "n_initialised": len(born),
        "n_converged": len(first_converged),
        "nees": nees,
        "first_nees": nees[:1],
        "depth_err": depth_err,
        "err": err,
        "on_block": on_block,
        "clean": clean,
        "n_matched": n_matched,
        "n_wrong": n_wrong,
    }


def chi2_mean_bounds(n: int, dof: int, two_sided: float = 0.95) -> tuple[float, float]:
    """Bounds for the mean of n independent chi-square(dof) values (Wilson-Hilferty, no scipy)."""
    k = n * dof
    z = 1.959963984540054 if two_sided == 0.95 else NotImplemented
    lo = k * (1 - 2 / (9 * k) - z * math.sqrt(2 / (9 * k))) ** 3
    hi = k * (1 - 2 / (9 * k) + z * math.sqrt(2 / (9 * k))) ** 3
    return lo / n, hi / n


_CACHE: dict[str, dict] = {}


def monte_carlo() -> dict:
    """All runs through both parameterisations (computed once per session)."""
    if _CACHE:
        return _CACHE
    for name in ("inverse_depth", "cartesian"):
        _CACHE[name] = {"runs": []}
    for seed in range(N_RUNS):
        world, frames = make_run(1000 + seed)
        for name in ("inverse_depth", "cartesian"):
            _CACHE[name]["runs"].append(play(world, frames, name))
    for name, res in _CACHE.items():
        runs = res["runs"]
        cat = {key: np.concatenate([r[key] for r in runs]) for key in ("frames_to_converge", "nees", "first_nees", "depth_err", "on_block")}
        res.update(cat)
        res["n_initialised"] = sum(r["n_initialised"] for r in runs)
        res["n_converged"] = sum(r["n_converged"] for r in runs)
        res["n_matched"] = sum(r["n_matched"] for r in runs)
        res["n_wrong"] = sum(r["n_wrong"] for r in runs)
    return _CACHE


def report() -> str:
    res = monte_carlo()
    lines = [f"mapper feature-level simulation: {N_RUNS} runs x {N_FRAMES} frames at {RATE_HZ:g} Hz, "
             f"sigma_p {SIGMA_POS_M} m, sigma_att {np.degrees(SIGMA_ATT_RAD):.2f} deg, pixel {PIXEL_SIGMA} px"]
    for name in ("inverse_depth", "cartesian"):
        r = res[name]
        f = r["frames_to_converge"]
        lo, hi = chi2_mean_bounds(len(r["nees"]), 3)
        lines.append(
            f"{name:>13}: converged {r['n_converged']}/{r['n_initialised']} features "
            f"({100 * r['n_converged'] / max(r['n_initialised'], 1):.0f}%), frames to converge median {np.median(f):.0f} "
            f"(p25 {np.percentile(f, 25):.0f}, p75 {np.percentile(f, 75):.0f}), final depth error median "
            f"{np.median(r['depth_err']):.2f} m (block points {np.median(r['depth_err'][r['on_block']]) if r['on_block'].any() else float('nan'):.2f} m, "
            f"n={int(r['on_block'].sum())}), mean NEES {r['nees'].mean():.2f} "
            f"(95% bounds for independent points {lo:.2f}..{hi:.2f}), one-per-run mean NEES {r['first_nees'].mean():.2f}, "
            f"wrong associations {r['n_wrong']}/{r['n_matched']}"
        )
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# Tests
# ----------------------------------------------------------------------------------------------


def test_inverse_depth_converges_to_the_truth_consistently():
    res = monte_carlo()["inverse_depth"]
    print("\n" + report())
    assert res["n_converged"] > 0.3 * res["n_initialised"]
    assert np.median(res["depth_err"]) < 1.0
    assert res["n_wrong"] <= 0.002 * res["n_matched"]
    lo, hi = chi2_mean_bounds(len(res["first_nees"]), 3)
    assert lo <= res["first_nees"].mean() <= hi, res["first_nees"].mean()


def test_inverse_depth_converges_faster_than_cartesian():
    res = monte_carlo()
    inv, cart = res["inverse_depth"], res["cartesian"]
    assert np.median(inv["frames_to_converge"]) < np.median(cart["frames_to_converge"])


if __name__ == "__main__":
    import time

    t0 = time.perf_counter()
    print(report())
    print(f"({time.perf_counter() - t0:.1f} s)")
