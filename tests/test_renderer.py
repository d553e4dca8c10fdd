"""The renderer: images are geometrically exact (known 3D corners land on Harris corners, the
z-buffer agrees with ray casting), textured where the scenario says, and fast."""

import time

import cv2
import numpy as np
import pytest

from companion.method.geometry import CameraMount, PinholeCamera, euler_to_matrix
from drivers.sim.renderer import Renderer, RenderOptions
from drivers.sim.textures import synthesize
from drivers.sim.world import World

CAMERA = PinholeCamera(625.3, 625.3, 319.5, 239.5, 640, 480)  # the paper's 42 deg vertical FOV, 640x480
DISTORTED = PinholeCamera(625.3, 625.3, 319.5, 239.5, 640, 480, distortion=np.array([-0.25, 0.08, 0.001, -0.001, 0.0]))
MOUNT = CameraMount.from_euler_deg(0.0, -45.0, 0.0)  # the paper's nose camera, 45 deg down

# Poses on or near the default circuit approaching the building (north, east, altitude, heading deg).
APPROACH = [(72.0, -3.0, 15.0, 5.0), (60.0, 0.0, 27.0, 0.0), (75.0, 8.0, 18.0, -20.0)]


def camera_pose(north, east, alt, heading_deg, mount=MOUNT):
    return mount.camera_pose(np.array([north, east, -alt]), euler_to_matrix(0.0, 0.0, np.radians(heading_deg)))


@pytest.fixture(scope="module")
def world():
    return World.load("default")


@pytest.fixture(scope="module")
def renderer(world):
    return Renderer(world, CAMERA)


@pytest.fixture(scope="module")
def flat():
    return World.from_dict({"name": "flat_small", "seed": 5, "ground": {"tile_px": 1024}}, "flat_small")


def harris(img, quality=0.001):
    """Harris corners as a detector would report them: integer peaks and sub-pixel refined."""
    c = cv2.goodFeaturesToTrack(img, 5000, quality, 3, blockSize=3, useHarrisDetector=True, k=0.04)
    refined = cv2.cornerSubPix(img, c.copy(), (3, 3), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    return c.reshape(-1, 2), refined.reshape(-1, 2)


# ---- geometry: known 3D corners ---------------------------------------------------------------------


@pytest.mark.parametrize("camera", [CAMERA, DISTORTED], ids=["pinhole", "distorted"])
def test_window_corners_project_onto_harris_corners(world, renderer, camera):
    r = renderer if camera is CAMERA else Renderer(world, camera)
    windows = world.window_corners_ned("building")
    n_checked, offsets = 0, []
    for pose in APPROACH:
        p_c, R_nc = camera_pose(*pose)
        img = r.render(p_c, R_nc)
        uv, visible = r.project(p_c, R_nc, windows, border_px=10)
        uv, visible = uv.reshape(-1, 4, 2), visible.reshape(-1, 4)
        # Windows big enough in the image that their corners are separate features.
        side = np.linalg.norm(uv - np.roll(uv, 1, axis=1), axis=2).min(axis=1)
        expected = uv[visible & (side[:, None] > 8)]
        assert len(expected) >= 40
        peaks, refined = harris(img)
        nearest = np.linalg.norm(expected[:, None] - refined[None], axis=2)
        assert nearest.min(axis=1).max() < 1.0  # every projected corner within 1 px of a detection
        d_peaks = np.linalg.norm(expected[:, None] - peaks[None], axis=2)
        assert d_peaks.min(axis=1).max() < 2.6  # integer peaks: Harris' own ~0.8 px diagonal bias
        offsets.append(refined[nearest.argmin(axis=1)] - expected)
        n_checked += len(expected)
    # No systematic shift (a half-pixel convention error would show here).
    assert np.all(np.abs(np.concatenate(offsets).mean(axis=0)) < 0.15)
    print(f"\n{camera is DISTORTED and 'distorted' or 'pinhole'}: {n_checked} window corners within 1 px "
          f"(median {np.median(np.linalg.norm(np.concatenate(offsets), axis=1)):.2f} px)")


def test_project_reports_occlusion(world, renderer):
    p_c, R_nc = camera_pose(60.0, 0.0, 27.0, 0.0)
    south = world.window_corners_ned("building")
    _, visible = renderer.project(p_c, R_nc, south)
    north_wall = np.isclose(south[:, 0], 110.0)
    south_wall = np.isclose(south[:, 0], 90.0)
    assert not np.any(visible[north_wall])  # behind the building
    assert np.any(visible[south_wall])
    _, behind = renderer.project(p_c, R_nc, p_c[None] - 5 * R_nc[:, 0])
    assert not behind[0]


def test_wall_above_the_windows_gives_no_corners(world, renderer):
    """The seed's map stopped at the windows: the renderer must not invent texture above them."""
    p_c, R_nc = camera_pose(60.0, 0.0, 27.0, 0.0)
    img = renderer.render(p_c, R_nc)
    peaks, _ = harris(img)

    def region_mask(alt_lo, alt_hi):
        quad = np.array([[90.0, -9.5, -alt_lo], [90.0, 9.5, -alt_lo], [90.0, 9.5, -alt_hi], [90.0, -9.5, -alt_hi]])
        uv, visible = renderer.project(p_c, R_nc, quad)
        assert np.all(visible)
        mask = np.zeros(img.shape, np.uint8)
        cv2.fillConvexPoly(mask, np.round(uv).astype(np.int32), 1)
        return cv2.erode(mask, np.ones((7, 7), np.uint8)).astype(bool)

    def count(mask):
        p = np.round(peaks).astype(int)
        return int(mask[p[:, 1], p[:, 0]].sum())

    plain, windows = region_mask(9.3, 11.7), region_mask(0.5, 8.7)
    assert plain.sum() > 2000 and count(plain) == 0
    assert count(windows) >= 40


# ---- geometry: depth -----------------------------------------------------------------------------


def test_depth_on_flat_ground_is_height_over_ray_down(flat):
    r = Renderer(flat, CAMERA)
    p_c, R_nc = camera_pose(10.0, 20.0, 15.0, 30.0)
    rng = r.depth(p_c, R_nc, along="ray")
    axis = r.depth(p_c, R_nc, along="axis")
    u, v = np.meshgrid(np.arange(640.0), np.arange(480.0))
    ray_c = np.stack([np.ones_like(u), (u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy], axis=-1)
    down = (ray_c @ R_nc.T)[..., 2]  # NED z of the ray with unit optical component
    np.testing.assert_allclose(axis, 15.0 / down, rtol=1e-5)
    np.testing.assert_allclose(rng, 15.0 / down * np.linalg.norm(ray_c, axis=-1), rtol=1e-5)
    # The optical axis (image centre) meets the ground 15 / sin 45 deg away.
    assert rng[239:241, 319:321].mean() == pytest.approx(15.0 * np.sqrt(2), rel=2e-3)


def test_depth_of_a_building_face(world, renderer):
    # Level camera facing north at the south wall (north = 90) from 30 m, 5 m up.
    p_c = np.array([60.0, 0.0, -5.0])
    rng = renderer.depth(p_c, np.eye(3), along="ray")
    axis = renderer.depth(p_c, np.eye(3), along="axis")
    assert axis[240, 320] == pytest.approx(30.0)
    # The wall is perpendicular to the axis: constant axial depth over its whole image.
    wall = (slice(100, 300), slice(150, 490))
    np.testing.assert_allclose(axis[wall], 30.0, rtol=1e-6)
    # Range = axial depth times the length of the pixel's ray with unit optical component.
    u = np.arange(150, 490)
    expected = 30.0 * np.sqrt(1 + ((u - CAMERA.cx) / CAMERA.fx) ** 2 + ((200 - CAMERA.cy) / CAMERA.fy) ** 2)
    np.testing.assert_allclose(rng[200, 150:490], expected, rtol=1e-6)
    # Above the roof (12 m, i.e. 7 m above the camera: v < c_v - f 7/30) the ray escapes over the
    # building and meets nothing.
    assert np.isinf(rng[50, 320])


@pytest.mark.parametrize("pose", APPROACH + [(200.0, 5.0, 15.0, 90.0), (140.0, 60.0, 15.0, 180.0)])
def test_zbuffer_agrees_with_raycast(renderer, pose):
    """The renderer's own occlusion (per-face homographies + z-buffer) matches exact ray casting
    everywhere except on silhouette pixels."""
    p_c, R_nc = camera_pose(*pose)
    _, z = renderer.render(p_c, R_nc, return_depth=True)
    truth = renderer.depth(p_c, R_nc, along="axis")
    rel = np.abs(z - truth) / truth
    assert np.mean(rel < 1e-3) > 0.998


def test_ground_texture_matches_direct_sampling(flat):
    """Per pixel: cast the ray to the ground, look the texel up in the tile, and compare. The view
    straddles a tile boundary (the tile is 51.2 m here), so the split-at-the-seam path is covered."""
    r = Renderer(flat, CAMERA)
    tile = synthesize(flat.ground_texture)
    mount = CameraMount.from_euler_deg(0.0, -70.0, 0.0)
    p_c, R_nc = camera_pose(51.2 - 3.0, 102.4 + 1.0, 8.0, 20.0, mount)
    img = r.render(p_c, R_nc)
    rays = r.pixel_rays(R_nc).reshape(-1, 3)
    X = p_c + (-p_c[2] / rays[:, 2])[:, None] * rays
    origin = flat.ground_tile_origin(np.zeros(2))
    a, b = flat.ground_axes
    col = (X - origin) @ a / (a @ a)
    row = (X - origin) @ b / (b @ b)
    period = tile.shape[0]
    assert col.min() < 2 * period < col.max() and row.min() < period < row.max()
    ref = cv2.remap(tile, np.mod(col, period).astype(np.float32).reshape(480, 640),
                    np.mod(row, period).astype(np.float32).reshape(480, 640), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_WRAP)
    diff = np.abs(img.astype(int) - ref.astype(int))
    assert diff.mean() < 1.0 and np.percentile(diff, 99.9) <= 8


# ---- appearance ------------------------------------------------------------------------------------


@pytest.mark.parametrize("alt", [15.0, 40.0])
def test_ground_gives_corners_everywhere(alt):
    world = World.load("flat")
    r = Renderer(world, CAMERA)
    p_c, R_nc = camera_pose(30.0, 40.0, alt, 60.0)
    img = r.render(p_c, R_nc)
    c = cv2.goodFeaturesToTrack(img, 2000, 0.01, 5, useHarrisDetector=True, k=0.04).reshape(-1, 2)
    counts, _, _ = np.histogram2d(c[:, 1], c[:, 0], bins=[4, 4], range=[[0, 480], [0, 640]])
    assert counts.min() >= 5, counts


def test_default_view_has_building_windows_and_many_corners(renderer, tmp_path):
    p_c, R_nc = camera_pose(72.0, -3.0, 15.0, 5.0)
    img = renderer.render(p_c, R_nc)
    c = cv2.goodFeaturesToTrack(img, 2000, 0.01, 5, useHarrisDetector=True, k=0.04)
    assert len(c) > 200
    assert 40 < img.mean() < 220 and img.std() > 25
    cv2.imwrite(str(tmp_path / "approach.png"), img)


def test_render_is_deterministic_and_seeded(flat):
    p_c, R_nc = camera_pose(0.0, 0.0, 15.0, 0.0)
    a = Renderer(flat, CAMERA).render(p_c, R_nc)
    b = Renderer(flat, CAMERA).render(p_c, R_nc)
    other = World.from_dict({"name": "flat_small", "seed": 6, "ground": {"tile_px": 1024}})
    c = Renderer(other, CAMERA).render(p_c, R_nc)
    assert np.array_equal(a, b)
    assert np.mean(np.abs(a.astype(int) - c.astype(int))) > 10


def test_noise_and_blur_options(flat):
    p_c, R_nc = camera_pose(0.0, 0.0, 15.0, 0.0)
    clean = Renderer(flat, CAMERA).render(p_c, R_nc).astype(float)
    noisy_r = Renderer(flat, CAMERA, RenderOptions(noise_sigma=3.0, seed=1))
    noisy = noisy_r.render(p_c, R_nc).astype(float)
    inside = (clean > 15) & (clean < 240)
    assert (noisy - clean)[inside].std() == pytest.approx(3.0, rel=0.15)
    assert not np.array_equal(noisy, noisy_r.render(p_c, R_nc))  # fresh noise each frame
    blurred = Renderer(flat, CAMERA, RenderOptions(blur_sigma_px=1.5)).render(p_c, R_nc).astype(float)
    assert np.abs(np.diff(blurred, axis=1)).mean() < 0.7 * np.abs(np.diff(clean, axis=1)).mean()
    with pytest.raises(ValueError):
        RenderOptions(noise_sigma=-1)
    with pytest.raises(ValueError):
        RenderOptions(near_m=10, far_m=5)


def test_sky_and_bad_poses(flat):
    r = Renderer(flat, CAMERA, RenderOptions(sky_gray=201))
    up = CameraMount.from_euler_deg(0.0, 60.0, 0.0)
    p_c, R_nc = camera_pose(0.0, 0.0, 15.0, 0.0, up)
    assert np.all(r.render(p_c, R_nc) == 201)
    below = r.render(np.array([0.0, 0.0, 5.0]), camera_pose(0, 0, 0, 0)[1])  # under the ground
    assert np.all(below == 201)
    with pytest.raises(ValueError):
        r.render(np.array([np.nan, 0.0, -10.0]), np.eye(3))


# ---- speed -----------------------------------------------------------------------------------------


def test_render_time_one_core(renderer):
    """Prints ms/frame on one core along the default circuit (the figure quoted in docs/sim.md)."""
    poses = [camera_pose(n, 0.0, 15.0, 0.0) for n in np.linspace(0, 200, 11)]
    poses += [camera_pose(200.0, e, 15.0, 90.0) for e in np.linspace(0, 60, 5)]
    poses += [camera_pose(*p) for p in APPROACH]
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        for p in poses[:3]:
            renderer.render(*p)
        times = []
        for _ in range(3):
            for p in poses:
                t0 = time.perf_counter()
                renderer.render(*p)
                times.append(time.perf_counter() - t0)
    finally:
        cv2.setNumThreads(threads)
    ms = np.array(times) * 1e3
    print(f"\nrender 640x480, one core: median {np.median(ms):.1f} ms, p90 {np.percentile(ms, 90):.1f} ms, "
          f"min {ms.min():.1f} ms over {len(ms)} frames")
    assert np.median(ms) < 40.0  # generous: the machine is shared; typical is a few ms
