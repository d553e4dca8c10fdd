"""Mapper throughput on rendered frames: frames per second at N features, the distance to the
floor (OpenCV's Harris response alone), the scaling with N, where the time goes, and the batched
code against the per-feature loop reference.

Every figure is the whole ``Mapper.step`` (detect -> undistort -> predict -> match -> update ->
initialise; with ``with_grid`` also the depth prior from the terrain map and the insertion of the
converged points), one core, OpenCV single-threaded, on the frames of
:func:`benchmarks.common.render_flight`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import ExitStack, contextmanager, nullcontext
from dataclasses import dataclass
from types import SimpleNamespace

import cv2
import numpy as np

from benchmarks import reference_loop
from benchmarks.common import Flight, mapper_config, summary
from companion.method.mapper import Mapper
from companion.method.mapper import features as features_module
from companion.method.mapper.appearance import FramePatches
from companion.method.mapper.features import HarrisDetector


def new_mapper(flight: Flight, n_features: int, depth_prior=None) -> Mapper:
    """A mapper of ``n_features`` with the flight's configuration."""
    cfg = mapper_config(n_features, flight.cfg.mapper)
    return Mapper(cfg, flight.camera, flight.mount, depth_prior=depth_prior,
                  default_ground_alt_m=flight.cfg.terrain.default_ground_alt_m, border_px=flight.cfg.camera.border_px)


def harris_floor_ms(gray: np.ndarray, cfg, out: np.ndarray) -> tuple[float, float]:
    """Wall and CPU time (ms) of OpenCV's Harris response alone on one grey frame, with the
    mapper's own parameters."""
    c0, t0 = time.thread_time(), time.perf_counter()
    cv2.cornerHarris(gray, cfg.harris_block_size, 3, cfg.harris_k, dst=out)
    return (time.perf_counter() - t0) * 1e3, (time.thread_time() - c0) * 1e3


@dataclass
class Variant:
    """One mapper configuration in an interleaved run: ``make()`` builds a fresh mapper;
    ``grid()`` (optional) a fresh TerrainGrid used as its depth prior and fed its points (as the
    daemon does; the insert is in the step time); ``context()`` (optional) is entered around each
    of its steps (outside the timed region), e.g. the loop reference's function swap."""

    make: Callable[..., Mapper]
    grid: Callable[[], object] | None = None
    context: Callable[[], object] | None = None


def variant(flight: Flight, n_features: int, grid=None, loop: bool = False) -> Variant:
    def make(prior=None):
        m = new_mapper(flight, n_features, prior)
        if loop:
            m.model = reference_loop.loop_model()
        return m

    return Variant(make, grid, reference_loop.loop_reference if loop else None)


def fresh_grid(flight: Flight) -> Callable[[], object]:
    """A factory of empty terrain maps of the flight's configuration (one per mapper run)."""
    from companion.method.terrain import TerrainGrid

    return lambda: TerrainGrid.from_config(flight.cfg.terrain)


def run_interleaved(flight: Flight, variants: dict, repeats: int = 1, warmup_frames: int = 30,
                    frames: int | None = None, with_floor: bool = False) -> dict:
    """Time ``Mapper.step`` of every variant over the flight, frame by frame in turn (the order
    rotates), ``repeats`` times with fresh mappers, so that the load of this shared machine falls
    on all of them alike. A warm-up pass over the first ``warmup_frames`` (untimed) comes first.
    ``with_floor`` also times ``cv2.cornerHarris`` alone on each frame (the floor).

    Returns, per variant name: per-frame step times (ms) of all repeats, wall-clock and CPU
    (``time.thread_time``: what the step cost this thread, without the time other processes of
    this shared machine held the core), throughput per repeat (frames / sum of step times) and
    the mean tracking counts; with ``with_floor`` each also has its ratio to the Harris floor.
    """
    n = len(flight) if frames is None else min(frames, len(flight))
    names = list(variants)

    def build(v: Variant):
        grid = v.grid() if v.grid is not None else None
        prior = None
        if grid is not None:
            max_range = flight.cfg.mapper.prior_max_range_m

            def prior(origin, rays, grid=grid):
                return grid.ray_range(origin, rays, max_range)

        return v.make(prior), grid

    def step(name, state, k):
        v = variants[name]
        mapper, grid = state
        ctx = v.context() if v.context is not None else nullcontext()
        with ctx:
            c0, t0 = time.thread_time(), time.perf_counter()
            s = mapper.step(flight.navs[k], flight.images[k])
            if grid is not None:
                grid.add_evidence(s.points, s.free_space, s.floors)
            dt, dc = time.perf_counter() - t0, time.thread_time() - c0
        return s, dt, dc

    warm = {name: build(variants[name]) for name in names}
    for k in range(min(warmup_frames, n)):
        for name in names:
            step(name, warm[name], k)
    step_ms = {name: [] for name in names}
    cpu_ms = {name: [] for name in names}
    totals = {name: [] for name in names}
    counts = {name: [] for name in names}
    floor_ms: list[float] = []
    floor_cpu_ms: list[float] = []
    buf = np.empty(flight.images[0].shape[:2], np.float32)
    base_cfg = flight.cfg.mapper
    for _ in range(repeats):
        state = {name: build(variants[name]) for name in names}
        total = dict.fromkeys(names, 0.0)
        for k in range(n):
            if with_floor:
                wall, cpu = harris_floor_ms(flight.images[k], base_cfg, buf)
                floor_ms.append(wall)
                floor_cpu_ms.append(cpu)
            for j in range(len(names)):
                name = names[(j + k) % len(names)]
                s, dt, dc = step(name, state[name], k)
                total[name] += dt
                step_ms[name].append(dt * 1e3)
                cpu_ms[name].append(dc * 1e3)
                counts[name].append((s.n_measurements, s.n_matched, s.n_initialised, s.n_active, len(s.points)))
        for name in names:
            totals[name].append(n / total[name])
    out = {}
    for name in names:
        c = np.asarray(counts[name], float).reshape(-1, 5)
        r = {
            "frames": n, "repeats": repeats, "step_ms": summary(step_ms[name]), "step_cpu_ms": summary(cpu_ms[name]),
            "fps_cpu": n / (sum(cpu_ms[name]) / 1e3 / repeats),
            "fps": float(np.median(totals[name])), "fps_repeats": [round(f, 1) for f in totals[name]],
            "measurements": float(c[:, 0].mean()), "matched": float(c[:, 1].mean()),
            "initialised": float(c[:, 2].mean()), "active": float(c[:, 3].mean()),
            "points_per_frame": float(c[:, 4].mean()), "_step_ms": step_ms[name],
        }
        if with_floor:
            per_frame = np.asarray(step_ms[name]) / np.asarray(floor_ms)
            r["harris_ms"] = summary(floor_ms)
            r["floor_ratio"] = r["step_ms"]["median"] / r["harris_ms"]["median"]
            r["floor_ratio_per_frame_median"] = float(np.median(per_frame))
            r["harris_cpu_ms"] = summary(floor_cpu_ms)
            r["floor_ratio_cpu"] = r["step_cpu_ms"]["median"] / r["harris_cpu_ms"]["median"]
        out[name] = r
    return out


def run_mapper(flight: Flight, n_features: int, repeats: int = 1, warmup_frames: int = 30, frames: int | None = None,
               with_floor: bool = False, grid=None) -> dict:
    """:func:`run_interleaved` of one mapper with ``n_features`` (``grid``: a TerrainGrid factory)."""
    r = run_interleaved(flight, {n_features: variant(flight, n_features, grid)}, repeats, warmup_frames, frames,
                        with_floor)[n_features]
    r["n_features"] = n_features
    return r


# ------------------------------------------------------------------------------------------------
# Where the time goes: timers wrapped around the functions a step calls
# ------------------------------------------------------------------------------------------------


class SectionTimer:
    """Accumulates the time of ``clock`` (wall by default; ``time.thread_time`` for this thread's
    CPU time) per named section; :meth:`wrap` returns a timing wrapper."""

    def __init__(self, clock=time.perf_counter):
        self.total: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.clock = clock

    def wrap(self, name: str, fn):
        total, calls, clock = self.total, self.calls, self.clock
        total.setdefault(name, 0.0)
        calls.setdefault(name, 0)

        def timed(*args, **kwargs):
            t0 = clock()
            try:
                return fn(*args, **kwargs)
            finally:
                total[name] += clock() - t0
                calls[name] += 1

        return timed


@contextmanager
def _patched(obj, name: str, timer: SectionTimer, label: str, missing: list):
    if not hasattr(obj, name):
        missing.append(label)
        yield
        return
    original = getattr(obj, name)
    setattr(obj, name, timer.wrap(label, original))
    try:
        yield
    finally:
        setattr(obj, name, original)


# (label, owner, attribute): detector stages, mapper stages in step order. The mapper module's
# functions are looked up there (it imports them by name); the model's through the mapper's model.
DETECTOR_SECTIONS = [
    ("detect: Harris response (cv2.cornerHarris)", HarrisDetector, "harris_response"),
    ("detect: valid region / black border", HarrisDetector, "valid_region"),
    ("detect: threshold (best response)", HarrisDetector, "response_threshold"),
    ("detect: local maxima above the level", HarrisDetector, "maxima_above"),
    ("detect: strongest candidates (partial sort)", features_module, "strongest"),
    ("detect: sub-pixel refine (cv2.cornerSubPix)", HarrisDetector, "refine"),
    ("detect: selection (greedy distance, bins, max)", features_module, "select_ordered"),
    ("appearance: patch descriptors", FramePatches, "rows"),
]
MAPPER_FUNCTIONS = [
    ("check_nav", "_checked_pose_covariance"),
    ("appearance: correlation of gated pairs", "pair_correlation"),
    ("navigation drift (process noise)", "navigation_drift"),
    ("match: innovation covariance S (eq. 10)", "innovation_covariance"),
    ("match: candidate pairs and their distances (eqs. 11-12)", "candidate_pairs"),
    ("match: gate and mutual nearest", "gate_and_match_pairs"),
    ("update: EKF (eqs. 7-9)", "ekf_update"),
    ("update: EKF across an edge", "ekf_update_across"),
    ("init: exclusion near stored features", "near_stored_pairs"),
    ("init: depth prior", "prior_ranges"),
]
MODEL_FUNCTIONS = [
    ("predict: direction terms of eq. 3 (shared)", "ray_directions"),
    ("navigation drift (process noise)", "navigation_frame_jacobian"),
    ("predict: measurement model (eqs. 3-4)", "measurement_model"),
    ("match: Jacobians (eq. 5)", "measurement_jacobian"),
    ("init: initialise features (eqs. 13-17)", "initialise_features"),
    ("converge: relative depth sigma and depth", "relative_depth_sigma"),
    ("converge: relative depth sigma and depth", "depth_from_origin"),
    ("bounds: free space and floors", "point"),
    ("bounds: free space and floors", "point_at_sigma"),
]
EDGELS = "edgels: detection (Canny in the bins without a corner)"
# Called by Mapper.step outside the measurement update ``Mapper._step_checked`` (with the detector).
OUTSIDE_MEASUREMENTS = ("check_nav", EDGELS)


def section_profile(flight: Flight, n_features: int, frames: int, clock=time.perf_counter) -> dict:
    """Mean ms per frame of each section of ``Mapper.step`` (timers around the functions it calls),
    plus the untimed rest: detector selection (greedy distance, bins) and the step's bookkeeping.
    ``clock``: wall time by default; ``time.thread_time`` gives CPU time (robust to the load of
    other processes)."""
    import companion.method.mapper.mapper as mapper_module

    n = min(frames, len(flight))
    mapper = new_mapper(flight, n_features)
    for k in range(min(30, n)):  # warm-up
        mapper.step(flight.navs[k], flight.images[k])
    mapper = new_mapper(flight, n_features)
    timer = SectionTimer(clock)
    missing: list[str] = []
    model = mapper.model
    mapper.model = SimpleNamespace(**{k: getattr(model, k) for k in dir(model) if not k.startswith("__")})
    with ExitStack() as stack:
        for label, owner, attr in DETECTOR_SECTIONS:
            stack.enter_context(_patched(owner, attr, timer, label, missing))
        for label, attr in MAPPER_FUNCTIONS:
            stack.enter_context(_patched(mapper_module, attr, timer, label, missing))
        for label, attr in MODEL_FUNCTIONS:
            stack.enter_context(_patched(mapper.model, attr, timer, label, missing))
        stack.enter_context(_patched(Mapper, "_emitted_points", timer, "emit: converged points out", missing))
        stack.enter_context(_patched(features_module, "detect_edgels", timer, EDGELS, missing))
        stack.enter_context(_patched(HarrisDetector, "__call__", timer, "_detector", missing))
        stack.enter_context(_patched(Mapper, "_step_checked", timer, "_measurements", missing))
        t0 = clock()
        for k in range(n):
            mapper.step(flight.navs[k], flight.images[k])
        wall = clock() - t0
    mapper.model = model
    per = {k: v / n * 1e3 for k, v in timer.total.items()}
    detector = per.pop("_detector", 0.0)
    measurements = per.pop("_measurements", 0.0)
    step = wall / n * 1e3
    outside = sum(per.get(k, 0.0) for k in OUTSIDE_MEASUREMENTS)
    det_parts = sum(v for k, v in per.items() if k.startswith("detect:"))
    # (the appearance patches are cut inside the measurement update, by FramePatches.rows)
    meas_parts = sum(v for k, v in per.items() if not k.startswith("detect:")) - outside
    rows = dict(per)
    rows["detect: the rest (batches, indexing)"] = detector - det_parts
    rows["step bookkeeping (database, masks, emission glue)"] = measurements - meas_parts
    rows["step: undistort, image checks, the rest"] = step - detector - measurements - outside
    return {"n_features": n_features, "frames": n, "step_ms_mean": step, "sections_ms": rows,
            "calls": dict(timer.calls), "not_found": missing}


def cprofile_top(flight: Flight, n_features: int, frames: int, top: int = 25) -> str:
    """cProfile of ``frames`` steps, sorted by own time (text)."""
    import cProfile
    import io
    import pstats

    mapper = new_mapper(flight, n_features)
    prof = cProfile.Profile()
    prof.enable()
    for k in range(min(frames, len(flight))):
        mapper.step(flight.navs[k], flight.images[k])
    prof.disable()
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(top)
    return s.getvalue()


# ------------------------------------------------------------------------------------------------
# Batched against the per-feature loop reference
# ------------------------------------------------------------------------------------------------


def record_match_inputs(flight: Flight, n_features: int, frames: int) -> list[dict]:
    """Inputs of the match+update part of each step, as the mapper had them: the stored features
    (states, covariances, reference rotations), the camera pose, P_x and the measurements."""
    from companion.method.mapper.projection import CameraPose

    mapper = new_mapper(flight, n_features)
    cfg = mapper.cfg
    detector = HarrisDetector(cfg, flight.camera.width, flight.camera.height, flight.cfg.camera.border_px)
    out = []
    for k in range(min(frames, len(flight))):
        nav, img = flight.navs[k], flight.images[k]
        uv, _ = detector(img)
        z = flight.camera.undistort(uv)
        slots = mapper.db.active_slots()
        P_x = nav.pose_covariance
        out.append({
            "y": mapper.db.y[slots].copy(), "P": mapper.db.P[slots].copy(), "R_ref": mapper.db.R_ref[slots].copy(),
            "pose": CameraPose.from_body(nav.position_ned_m, nav.R_nb, flight.mount),
            "P_x": 0.5 * (P_x + P_x.T), "z": z[flight.camera.in_image(z)],
        })
        mapper.step_measurements(nav, z)
    return out


def match_update(model, fns, inp: dict, camera, cfg, R_img) -> tuple:
    """Predict -> drop the invisible -> Jacobians -> S -> candidate pairs and their distances ->
    gate -> update -> exclusion, with the given model (measurement model and Jacobian) and functions
    (matching and update), as ``Mapper.step_measurements`` does them (without appearance)."""
    y, P, R_ref, pose, P_x, z = inp["y"], inp["P"], inp["R_ref"], inp["pose"], inp["P_x"], inp["z"]
    uv, h = model.measurement_model(y, R_ref, pose, camera)
    vis = (h[:, 0] > 0) & camera.in_image(uv)
    y, P, R_ref, uv, h = y[vis], P[vis], R_ref[vis], uv[vis], h[vis]
    C_x, C_y = model.measurement_jacobian(y, R_ref, pose, camera, h)
    S = fns.innovation_covariance(C_x, C_y, P_x, P, R_img)
    pairs = fns.candidate_pairs(z, uv, S, max(cfg.gate_chi2, cfg.init_exclusion_chi2), cfg.min_distance_px)
    pi, mi, ambiguous = fns.gate_and_match_pairs(pairs.point, pairs.meas, pairs.Z, cfg.gate_chi2, len(z))
    y1, P1, ok = fns.ekf_update(y[pi], P[pi], z[mi] - uv[pi], C_x[pi], C_y[pi], P_x, R_img)
    blocked = ambiguous | fns.near_stored_pairs(pairs, len(z), cfg.init_exclusion_chi2, cfg.min_distance_px)
    return y1, P1, ok, pi, mi, blocked


def batched_functions():
    from companion.method.mapper import inverse_depth, matching, update

    fns = SimpleNamespace(innovation_covariance=matching.innovation_covariance,
                          candidate_pairs=matching.candidate_pairs,
                          gate_and_match_pairs=matching.gate_and_match_pairs,
                          near_stored_pairs=matching.near_stored_pairs,
                          ekf_update=update.ekf_update)
    return inverse_depth, fns


def compare_match_update(flight: Flight, n_features: int, frames: int, repeats: int = 3) -> dict:
    """Time the match+update part, batched and loop, on the same recorded inputs; check they agree."""
    inputs = record_match_inputs(flight, n_features, frames)
    inputs = [i for i in inputs if len(i["y"])]
    cfg = mapper_config(n_features, flight.cfg.mapper)
    R_img = np.diag([cfg.pixel_sigma_px**2] * 2)
    b_model, b_fns = batched_functions()
    l_model, l_fns = reference_loop.loop_model(), reference_loop
    max_dy, same_matches = 0.0, 0
    for inp in inputs:
        a = match_update(b_model, b_fns, inp, flight.camera, cfg, R_img)
        b = match_update(l_model, l_fns, inp, flight.camera, cfg, R_img)
        if all(np.array_equal(x, w) for x, w in zip(a[2:], b[2:])):
            same_matches += 1
            if len(a[0]):
                max_dy = max(max_dy, float(np.max(np.abs(a[0] - b[0]))), float(np.max(np.abs(a[1] - b[1]))))
    per_frame = {"batched": [], "loop": []}
    impls = {"batched": (b_model, b_fns), "loop": (l_model, l_fns)}
    for r in range(repeats):
        for k, inp in enumerate(inputs):
            for name in (("batched", "loop") if (k + r) % 2 == 0 else ("loop", "batched")):
                model, fns = impls[name]
                t0 = time.perf_counter()
                match_update(model, fns, inp, flight.camera, cfg, R_img)
                per_frame[name].append((time.perf_counter() - t0) * 1e3)
    times = {name: summary(v) for name, v in per_frame.items()}
    return {
        "n_features": n_features, "frames": len(inputs),
        "features_mean": float(np.mean([len(i["y"]) for i in inputs])),
        "measurements_mean": float(np.mean([len(i["z"]) for i in inputs])),
        "batched_ms": times["batched"], "loop_ms": times["loop"],
        "speedup": times["loop"]["median"] / times["batched"]["median"],
        "identical_decisions": f"{same_matches}/{len(inputs)}", "max_abs_state_difference": max_dy,
    }


def compare_whole_step(flight: Flight, n_features: int, frames: int) -> dict:
    """The whole ``Mapper.step`` with the batched equations and with the loop reference,
    interleaved frame by frame on the same frames."""
    r = run_interleaved(flight, {"batched": variant(flight, n_features), "loop": variant(flight, n_features, loop=True)},
                        repeats=1, warmup_frames=10, frames=frames)
    b, lp = r["batched"], r["loop"]
    return {
        "n_features": n_features, "frames": b["frames"],
        "batched_step_ms": b["step_ms"], "loop_step_ms": lp["step_ms"],
        "batched_fps": b["fps"], "loop_fps": lp["fps"],
        "speedup": lp["step_ms"]["median"] / b["step_ms"]["median"],
        "matched_mean": (b["matched"], lp["matched"]),
    }


# ------------------------------------------------------------------------------------------------
# The N x M matching: dense matrices against candidate pairs (what changed, measured in the run)
# ------------------------------------------------------------------------------------------------


def dense_matching(z: np.ndarray, g: np.ndarray, S: np.ndarray, cfg) -> tuple:
    """Eqs. 11-12, gate, mutual nearest and exclusion on the dense ``(N, M)`` matrices, as the
    mapper did them before the batched matching (``einsum`` over ``(N, M, 2)`` differences and a
    second ``(N, M, 2)`` array for the pixel distances)."""
    from companion.method.mapper.matching import gate_and_match, inverse_2x2

    S_inv, ok = inverse_2x2(S)
    e = z[None, :, :] - g[:, None, :]
    Z = np.einsum("nmi,nij,nmj->nm", e, S_inv, e)
    Z[~ok, :] = np.inf
    point_idx, meas_idx, ambiguous = gate_and_match(Z, cfg.gate_chi2)
    if len(g) and len(z):
        near = ((Z < cfg.init_exclusion_chi2) | (np.sum(e**2, axis=2) < cfg.min_distance_px**2)).any(axis=0)
    else:
        near = np.zeros(len(z), dtype=bool)
    return point_idx, meas_idx, ambiguous | near


def pair_matching(z: np.ndarray, g: np.ndarray, S: np.ndarray, cfg) -> tuple:
    """The same decisions from candidate pairs (``companion.method.mapper.matching``), as the mapper runs them."""
    from companion.method.mapper import matching

    pairs = matching.candidate_pairs(z, g, S, max(cfg.gate_chi2, cfg.init_exclusion_chi2), cfg.min_distance_px)
    point_idx, meas_idx, ambiguous = matching.gate_and_match_pairs(pairs.point, pairs.meas, pairs.Z, cfg.gate_chi2, len(z))
    near = matching.near_stored_pairs(pairs, len(z), cfg.init_exclusion_chi2, cfg.min_distance_px)
    return point_idx, meas_idx, ambiguous | near


def matching_comparison(flight: Flight, n_features: int, frames: int) -> dict:
    """:func:`dense_matching` against :func:`pair_matching`, interleaved on the recorded inputs of
    real steps (stored features' predictions and S, the frame's measurements); checks that every
    decision (matches, ambiguous and excluded measurements) is the same."""
    inputs = [i for i in record_match_inputs(flight, n_features, frames) if len(i["y"])]
    cfg = mapper_config(n_features, flight.cfg.mapper)
    R_img = np.diag([cfg.pixel_sigma_px**2] * 2)
    model, fns = batched_functions()
    cases = []
    for inp in inputs:
        uv, h = model.measurement_model(inp["y"], inp["R_ref"], inp["pose"], flight.camera)
        vis = (h[:, 0] > 0) & flight.camera.in_image(uv)
        C_x, C_y = model.measurement_jacobian(inp["y"][vis], inp["R_ref"][vis], inp["pose"], flight.camera, h[vis])
        S = fns.innovation_covariance(C_x, C_y, inp["P_x"], inp["P"][vis], R_img)
        cases.append((inp["z"], uv[vis], S))
    times = {"dense": [], "pairs": []}
    same = 0
    for k, (z, g, S) in enumerate(cases):
        out = {}
        for name in (("dense", "pairs") if k % 2 == 0 else ("pairs", "dense")):
            fn = dense_matching if name == "dense" else pair_matching
            t0 = time.perf_counter()
            out[name] = fn(z, g, S, cfg)
            times[name].append((time.perf_counter() - t0) * 1e3)
        same += all(np.array_equal(a, b) for a, b in zip(out["dense"], out["pairs"]))
    a, b = summary(times["dense"]), summary(times["pairs"])
    return {"n_features": n_features, "frames": len(cases), "dense_ms": a, "pairs_ms": b,
            "saved_ms_median": a["median"] - b["median"], "speedup": a["median"] / b["median"],
            "identical_decisions": f"{same}/{len(cases)}",
            "pairs_per_frame": float(np.mean([len(S) * len(z) for z, _, S in cases]))}
