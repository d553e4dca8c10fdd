"""Tracking between detections (docs/mapper.md, "Tracking between detections"): pyramidal
Lucas-Kanade follows each corner that measured a feature into the next frame, as a measurement
beside the detector's corners. Real OpenCV on rendered frames of the default scenario."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from benchmarks.common import RATE_HZ, body_pose, nav_covariance, render_flight
from companion.method.geometry import matrix_to_quat
from companion.method.mapper import Mapper
from companion.method.mapper.features import HarrisDetector
from companion.method.messages import NavState


class FirstFrameOnly:
    """The Harris detector on the first frame, nothing after: every later measurement is the tracker's."""

    def __init__(self, detector: HarrisDetector):
        self.detector, self.calls = detector, 0

    def __call__(self, image):
        self.calls += 1
        if self.calls == 1:
            return self.detector(image)
        return np.zeros((0, 2)), np.zeros(0)


@pytest.fixture(scope="module")
def flight():
    return render_flight(6)


def run(flight, window_px: int) -> tuple[Mapper, list]:
    cfg = dataclasses.replace(flight.cfg.mapper, track_window_px=window_px, max_edgels=0)
    W, H = flight.camera.width, flight.camera.height
    detector = FirstFrameOnly(HarrisDetector(cfg, W, H, flight.cfg.camera.border_px))
    mapper = Mapper(cfg, flight.camera, flight.mount, detector=detector, border_px=flight.cfg.camera.border_px)
    steps = []
    for k, image in enumerate(flight.images):
        t = k / RATE_HZ  # render_flight's frame times; the true pose (its errors are the navigation's test)
        p, R_nb, v = body_pose(t)
        nav = NavState(t, p, v, matrix_to_quat(R_nb), nav_covariance())
        steps.append((mapper.step(nav, image), mapper.last_measurements_raw.copy()))
    return mapper, steps


def test_the_tracker_keeps_measuring_features_the_detector_does_not_find_again(flight):
    """After the first frame the detector finds nothing: without the tracker no feature is measured
    again; with it, most features are, every frame, and no tracked point starts a feature."""
    _, plain = run(flight, 0)
    _, tracked = run(flight, 15)
    born = plain[0][0].n_initialised
    assert born >= 30 and tracked[0][0].n_initialised == born
    assert all(step.n_matched == 0 for step, _ in plain[1:])
    for step, _ in tracked[1:]:
        assert step.n_matched >= 0.8 * born
        assert step.n_initialised == 0


def test_a_tracked_point_lands_where_the_surface_point_projects(flight):
    """Each feature's first-frame corner is a point of the rendered world (its ray cast from the
    first camera); its tracked measurements in the next frames sit on that point's projection
    to a few tenths of a pixel (the renderer's noise and the corner's own localisation)."""
    from drivers.sim.world import World

    world = World.load(flight.cfg.sim.scenario)
    mapper, steps = run(flight, 15)
    cam, mount = flight.camera, flight.mount

    def camera_at(k):
        p, R_nb, _ = body_pose(k / RATE_HZ)
        return mount.camera_pose(p, R_nb)

    first, uv0 = steps[0]
    p0, R0 = camera_at(0)
    start = cam.undistort(uv0[first.initialised_measurements])
    rays = cam.ray(start) @ R0.T
    r = world.raycast(p0, rays)
    points = {int(f): p0 + r[i] * rays[i] for i, f in enumerate(first.initialised_ids) if np.isfinite(r[i])}
    errors = []
    for k, (step, uv) in enumerate(steps[1:], start=1):
        p_c, R_nc = camera_at(k)
        for f, m in zip(step.matched_ids.tolist(), step.matched_measurements.tolist()):
            if f in points:
                truth = cam.project((points[f] - p_c) @ R_nc)
                errors.append(np.linalg.norm(cam.undistort(uv[m : m + 1])[0] - truth))
    errors = np.array(errors)
    assert len(errors) >= 60
    assert np.median(errors) < 0.3 and np.percentile(errors, 95) < 1.0


def test_a_tracked_point_updates_its_feature_but_keeps_the_detectors_patch(flight):
    """The appearance check compares a tracked point with the patch of the feature's last detected
    corner, not with the tracker's own window of the frame before: a slow drift cannot carry the
    patch with it. The estimate itself is updated."""
    cfg = dataclasses.replace(flight.cfg.mapper, track_window_px=15, max_edgels=0)
    W, H = flight.camera.width, flight.camera.height
    mapper = Mapper(cfg, flight.camera, flight.mount, detector=FirstFrameOnly(HarrisDetector(cfg, W, H, flight.cfg.camera.border_px)),
                    border_px=flight.cfg.camera.border_px)
    before = None
    for k, image in enumerate(flight.images[:3]):
        p, R_nb, v = body_pose(k / RATE_HZ)
        step = mapper.step(NavState(k / RATE_HZ, p, v, matrix_to_quat(R_nb), nav_covariance()), image)
        slots = mapper.db.active_slots()
        if before is None:
            before = {int(i): (mapper.db.template[s].copy(), mapper.db.y[s].copy()) for i, s in zip(mapper.db.ids[slots], slots)}
            continue
        assert step.n_matched > 0
        for i in step.matched_ids.tolist():
            s = int(np.flatnonzero(mapper.db.ids == i)[0])
            np.testing.assert_array_equal(mapper.db.template[s], before[i][0])
            assert not np.array_equal(mapper.db.y[s], before[i][1])
