"""Render the simulated world: camera pose + intrinsics -> grayscale image, in milliseconds.

Every surface is planar, so each face maps to the image by a homography (a plane seen by a
pinhole camera). For a face whose texel (col, row) sits at ``X = O + col a + row b`` (NED), the
pixel is, with ``M = K P R_nc^T`` (``P`` = paper-to-OpenCV axes, seed 000 eq. 4),

    [u v 1]^T ~ M (X - p_c) = M [a  b  O - p_c] [col row 1]^T,

and ``cv2.warpPerspective`` draws the texture with that 3x3 matrix, restricted to the bounding
box of the face's projection. Before warping, each face polygon is clipped to the view frustum
(near plane and the four image edges) and cut into depth bands an octave apart; each band
samples the texture's mip level whose texels project to about one pixel (no aliasing at range).

Occlusion: the ground is drawn first (any structure on a ray going down is in front of the
ground), then every structure face is drawn with a per-pixel depth test. The inverse depth of a
plane is affine in pixel coordinates, ``1/z = n_c . [1, (u-c_u)/f_u, (v-c_v)/f_v] / (d - n . p_c)``,
so the z-buffer costs one add per pixel of the face's box.

Lens distortion: the ideal image is rendered on a canvas large enough to cover every raw pixel's
undistorted position, then resampled with ``cv2.remap``. Optional sensor blur and noise.

Ground truth: :meth:`Renderer.depth` ray-casts every pixel against the world's exact geometry
(slow, for tests); :meth:`Renderer.project` gives raw pixel positions of 3D points and whether
they are visible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from companion.method.geometry import PAPER_TO_OPENCV, PinholeCamera
from drivers.sim.textures import synthesize
from drivers.sim.world import UP, Face, TextureSpec, World


@dataclass(frozen=True, slots=True)
class RenderOptions:
    """near_m/far_m: clip depths; sky_gray: what lies beyond the far plane or above the horizon;
    noise_sigma: additive Gaussian sensor noise (gray levels); blur_sigma_px: optical blur;
    seed: noise seed."""

    near_m: float = 0.25
    far_m: float = 1500.0
    sky_gray: int = 200
    noise_sigma: float = 0.0
    blur_sigma_px: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.near_m < self.far_m:
            raise ValueError(f"need 0 < near_m < far_m, got {self.near_m}, {self.far_m}")
        if not 0 <= self.sky_gray <= 255:
            raise ValueError(f"sky_gray must be in [0, 255], got {self.sky_gray}")
        if not (self.noise_sigma >= 0 and self.blur_sigma_px >= 0):
            raise ValueError("noise_sigma and blur_sigma_px must be >= 0")


class _Surface:
    """A drawable plane: polygon, mapping texel -> NED, and the texture's mip pyramid."""

    def __init__(self, vertices, normal, offset, origin, axis_u, axis_v, texture: np.ndarray | None, wrap: bool,
                 zero_depth: bool, pyramid: list[np.ndarray] | None = None, shade: float = 1.0):
        self.vertices = vertices
        self.normal = normal
        self.offset = offset
        self.origin = origin
        self.axis_u = axis_u
        self.axis_v = axis_v
        self.texel_m = math.sqrt(np.linalg.norm(axis_u) * np.linalg.norm(axis_v))
        self.wrap = wrap
        self.zero_depth = zero_depth  # the ground: drawn first, never occludes
        self.shade = shade  # applied when drawing (textures shared between surfaces)
        if pyramid is not None:
            self.pyramid = pyramid
            return
        self.pyramid = [texture]
        while min(self.pyramid[-1].shape) >= 16 and len(self.pyramid) < 10:
            if wrap and any(s % 2 for s in self.pyramid[-1].shape):
                break  # keep the wrap period an exact number of texels at every level
            self.pyramid.append(cv2.pyrDown(self.pyramid[-1], borderType=cv2.BORDER_WRAP if wrap else cv2.BORDER_REFLECT101))


def _clip(poly: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: keep the part of convex polygon ``poly`` (M, 3) where the affine
    function with vertex values ``f`` (M,) is >= 0."""
    lo, hi = f.min(), f.max()
    if lo >= 0:
        return poly
    if hi < 0:
        return poly[:0]
    out = []
    m = len(poly)
    fl = f.tolist()
    for k in range(m):
        j = k + 1 if k + 1 < m else 0
        fk, fj = fl[k], fl[j]
        if fk >= 0:
            out.append(poly[k])
        if (fk >= 0) != (fj >= 0):
            out.append(poly[k] + (fk / (fk - fj)) * (poly[j] - poly[k]))
    return np.array(out)


class Renderer:
    """Renders :class:`World` through a :class:`PinholeCamera` (paper camera frame: x optical, y right, z down).

    Build once (textures are synthesised here, ~1 s for the default scenario), then call
    :meth:`render` per frame. Not thread-safe: one render at a time per instance.
    """

    def __init__(self, world: World, camera: PinholeCamera, options: RenderOptions | None = None):
        self.world = world
        self.camera = camera
        self.options = options or RenderOptions()
        self._canvas_camera, self._distort_maps = self._canvas(camera)
        ground = world.ground_texture
        self._ground = _Surface(None, UP.copy(), 0.0, None, *world.ground_axes, self._texture(ground), True, True)
        self._faces = [self._surface(f) for f in world.faces]
        rng = np.random.default_rng(self.options.seed)
        self._noise_rng = rng
        if self.options.noise_sigma > 0:
            bank = rng.standard_normal((2 * camera.height, 2 * camera.width), dtype=np.float32) * self.options.noise_sigma
            self._noise_bank = np.round(bank).astype(np.int16)

    @staticmethod
    def _texture(spec: TextureSpec) -> np.ndarray:
        if spec.kind == "plain" and spec.wrap:
            # A plain ground still needs to exist; keep it small.
            spec = TextureSpec("plain", 256, 256, spec.texel_m, spec.seed, spec.shade, None, True)
        return synthesize(spec)

    def _surface(self, f: Face) -> _Surface:
        if f.texture.kind == "ground":  # draped ground: share the ground's pyramid, shade when drawing
            return _Surface(f.vertices_ned, f.normal_ned, f.offset, f.origin_ned, f.axis_u_ned, f.axis_v_ned,
                            None, True, False, pyramid=self._ground.pyramid, shade=f.texture.shade)
        return _Surface(f.vertices_ned, f.normal_ned, f.offset, f.origin_ned, f.axis_u_ned, f.axis_v_ned,
                        self._texture(f.texture), False, False)

    @staticmethod
    def _canvas(camera: PinholeCamera):
        """Ideal-image canvas covering every raw pixel's undistorted position, and the remap tables."""
        if not camera.has_distortion:
            return camera, None
        w, h = camera.width, camera.height
        uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        ideal = camera.undistort(np.column_stack([uu.ravel(), vv.ravel()])).reshape(h, w, 2)
        if not np.all(np.isfinite(ideal)):
            raise ValueError("camera distortion cannot be inverted over the image")
        lo = np.floor(ideal.reshape(-1, 2).min(axis=0)) - 2
        hi = np.ceil(ideal.reshape(-1, 2).max(axis=0)) + 2
        lo = np.maximum(lo, [-w, -h])
        hi = np.minimum(hi, [2 * w, 2 * h])
        canvas = PinholeCamera(camera.fx, camera.fy, camera.cx - lo[0], camera.cy - lo[1],
                               int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1)
        map_x = (ideal[..., 0] - lo[0]).astype(np.float32)
        map_y = (ideal[..., 1] - lo[1]).astype(np.float32)
        return canvas, cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)

    # ---- rendering ------------------------------------------------------------------------------

    def render(self, p_c: np.ndarray, R_nc: np.ndarray, return_depth: bool = False):
        """Grayscale image (H, W) uint8 seen from camera centre ``p_c`` (3,) NED with attitude
        ``R_nc`` (3, 3) (paper camera frame -> NED).

        With ``return_depth`` also the renderer's own z-buffer as depth along the optical axis
        (H, W) float32 (inf where nothing is drawn), for checking occlusion against :meth:`depth`.
        """
        p_c = np.asarray(p_c, float).reshape(3)
        R_nc = np.asarray(R_nc, float).reshape(3, 3)
        if not (np.all(np.isfinite(p_c)) and np.all(np.isfinite(R_nc))):
            raise ValueError("camera pose must be finite")
        cam = self._canvas_camera
        img = np.full((cam.height, cam.width), self.options.sky_gray, np.uint8)
        inv_z = np.zeros((cam.height, cam.width), np.float32)
        view = _View(cam, p_c, R_nc, self.options)
        self._draw(view, self._ground, self._ground_polygon(p_c), img, inv_z, return_depth)
        for s in self._faces:
            if s.normal @ (p_c - s.vertices[0]) > 1e-9:  # back faces are never seen
                self._draw(view, s, s.vertices, img, inv_z, True)
        depth = None
        if return_depth:
            with np.errstate(divide="ignore"):
                depth = np.where(inv_z > 0, 1.0 / inv_z, np.inf).astype(np.float32)
        if self._distort_maps is not None:
            img = cv2.remap(img, *self._distort_maps, cv2.INTER_LINEAR)
            if return_depth:
                depth = cv2.remap(depth, *self._distort_maps, cv2.INTER_NEAREST)
        img = self._sensor(img)
        return (img, depth) if return_depth else img

    def _ground_polygon(self, p_c: np.ndarray) -> np.ndarray:
        """A square of the ground plane around the camera, wide enough to reach the far plane."""
        r = 2.0 * self.options.far_m
        n, e = p_c[0], p_c[1]
        return np.array([[n - r, e - r, 0.0], [n - r, e + r, 0.0], [n + r, e + r, 0.0], [n + r, e - r, 0.0]])

    def _draw(self, view: "_View", s: _Surface, polygon: np.ndarray, img: np.ndarray, inv_z: np.ndarray,
              write_depth: bool) -> None:
        """Draw one surface: clip to the frustum, split into depth bands, warp each band's mip level."""
        # Clip to the frustum: all six planes tested at once, clipping only where a vertex is outside.
        f = (polygon - view.p_c) @ view.planes_n - view.planes_d
        if np.any(f.max(axis=0) < 0):
            return
        poly = polygon
        for k in np.nonzero(f.min(axis=0) < 0)[0]:
            poly = _clip(poly, (poly - view.p_c) @ view.planes_n[:, k] - view.planes_d[k])
            if len(poly) < 3:
                return
        z = (poly - view.p_c) @ view.axis
        z_lo, z_hi = max(z.min(), view.near), min(z.max(), view.far)
        if z_lo > z_hi:
            return
        # Depth bands an octave apart, starting where a texel projects to one pixel head-on.
        z0 = view.f * s.texel_m
        edges = [z_lo]
        if z_hi > z0:
            k = max(0, math.floor(math.log2(max(z_lo, 1e-9) / z0)) + 1)
            while z0 * 2**k < z_hi:
                if z0 * 2**k > z_lo:
                    edges.append(z0 * 2**k)
                k += 1
        edges.append(z_hi)
        bands = []
        for a, b in zip(edges[:-1], edges[1:]):
            near_cut = _clip(poly, z - a) if a > z_lo else poly
            band = _clip(near_cut, b - (near_cut - view.p_c) @ view.axis) if b < z_hi and len(near_cut) >= 3 else near_cut
            if len(band) >= 3:
                bands.append(band)
        # Merge neighbouring bands that sample the same mip level.
        merged: list[tuple[int, list[np.ndarray]]] = []
        for band in bands:
            level = self._mip_level(view, s, band)
            if merged and merged[-1][0] == level:
                merged[-1][1].append(band)
            else:
                merged.append((level, [band]))
        for level, parts in merged:
            if s.zero_depth and level <= 2:
                # Sampling across the tile's edge takes OpenCV's slow border path: cut the near ground
                # along tile boundaries and warp each piece from its own tile origin.
                for origin, pieces in self._tile_pieces(parts):
                    self._warp(view, s, level, pieces, origin, img, inv_z, write_depth)
            else:
                origin = s.origin if s.origin is not None else self.world.ground_tile_origin(view.p_c[:2])
                self._warp(view, s, level, parts, origin, img, inv_z, write_depth)

    def _warp(self, view: "_View", s: _Surface, level: int, parts: list[np.ndarray], origin: np.ndarray,
              img: np.ndarray, inv_z: np.ndarray, write_depth: bool) -> None:
        """Warp mip ``level`` of the surface's texture into the pixels covered by convex ``parts``."""
        uv = [view.project(part) for part in parts]
        allv = np.vstack(uv)
        x0, y0 = np.floor(allv.min(axis=0)).astype(int)
        x1, y1 = np.ceil(allv.max(axis=0)).astype(int)
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, img.shape[1] - 1), min(y1, img.shape[0] - 1)
        if x1 < x0 or y1 < y0:
            return
        w, h = x1 - x0 + 1, y1 - y0 + 1
        mask = np.zeros((h, w), np.uint8)
        for q in uv:
            cv2.fillConvexPoly(mask, np.round((q - [x0, y0]) * 16).astype(np.int32), 1, cv2.LINE_8, 4)
        scale = 2.0**level
        H = view.M @ np.column_stack([s.axis_u * scale, s.axis_v * scale, origin - view.p_c])
        H = np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1.0]]) @ H
        warped = cv2.warpPerspective(s.pyramid[level], H, (w, h), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_WRAP if s.wrap else cv2.BORDER_REPLICATE)
        if s.shade != 1.0:
            warped = cv2.convertScaleAbs(warped, alpha=s.shade)
        sel = mask.view(bool)
        if s.zero_depth and not write_depth:
            np.copyto(img[y0:y1 + 1, x0:x1 + 1], warped, where=sel)
            return
        plane_inv = view.inverse_depth(s.normal, s.offset, x0, y0, w, h)
        zb = inv_z[y0:y1 + 1, x0:x1 + 1]
        if not s.zero_depth:
            sel &= plane_inv > zb
        np.copyto(img[y0:y1 + 1, x0:x1 + 1], warped, where=sel)
        np.copyto(zb, plane_inv, where=sel)

    def _tile_pieces(self, parts: list[np.ndarray]):
        """Cut ground polygons along the texture tile boundaries: [(tile origin, [pieces])]."""
        period = self.world.ground_period_m
        allv = np.vstack(parts)
        k_lo = np.floor(allv[:, :2].min(axis=0) / period).astype(int)
        k_hi = np.floor(allv[:, :2].max(axis=0) / period).astype(int)
        if np.all(k_lo == k_hi):
            return [(self.world.ground_tile_origin(allv[0, :2]), parts)]
        out = []
        for i in range(k_lo[0], k_hi[0] + 1):
            for j in range(k_lo[1], k_hi[1] + 1):
                pieces = []
                for part in parts:
                    q = part
                    for axis, lo in ((0, i * period), (1, j * period)):
                        if len(q) >= 3:
                            q = _clip(q, q[:, axis] - lo)
                        if len(q) >= 3:
                            q = _clip(q, lo + period - q[:, axis])
                    if len(q) >= 3:
                        pieces.append(q)
                if pieces:
                    out.append((self.world.ground_tile_origin(np.array([i + 0.5, j + 0.5]) * period), pieces))
        return out

    def _mip_level(self, view: "_View", s: _Surface, band: np.ndarray) -> int:
        """Pyramid level whose texels project to about a pixel: geometric mean of the two
        directions, the oblique one foreshortened by the cosine of incidence."""
        centre = band.mean(axis=0) - view.p_c
        dist = np.linalg.norm(centre)
        z = max(centre @ view.axis, view.near)
        cos_inc = max(abs(centre @ s.normal) / max(dist, 1e-9), 0.05)
        texel_px = view.f * s.texel_m / z * math.sqrt(cos_inc)
        level = math.floor(math.log2(1.0 / texel_px)) if texel_px < 1.0 else 0
        return min(max(level, 0), len(s.pyramid) - 1)

    def _sensor(self, img: np.ndarray) -> np.ndarray:
        o = self.options
        if o.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (0, 0), o.blur_sigma_px)
        if o.noise_sigma > 0:
            h, w = img.shape
            dy, dx = self._noise_rng.integers(0, h), self._noise_rng.integers(0, w)
            noise = self._noise_bank[dy:dy + h, dx:dx + w]
            img = cv2.add(img, noise, dtype=cv2.CV_8U)
        return img

    # ---- ground truth ---------------------------------------------------------------------------

    def pixel_rays(self, R_nc: np.ndarray) -> np.ndarray:
        """Unit NED ray of every raw pixel (H, W, 3) (through the lens model when distorted)."""
        cam = self.camera
        uu, vv = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
        uv = cam.undistort(np.column_stack([uu.ravel(), vv.ravel()]))
        rays_c = cam.ray(uv)
        return (rays_c @ np.asarray(R_nc, float).T).reshape(cam.height, cam.width, 3)

    def depth(self, p_c: np.ndarray, R_nc: np.ndarray, along: Literal["ray", "axis"] = "ray") -> np.ndarray:
        """Exact ground-truth depth of every raw pixel (H, W) float32 by ray casting (slow: ~1 s).

        along="ray": range from the camera centre along the pixel's ray (m);
        along="axis": depth along the optical axis (the paper camera frame's x), ``range * cos``.
        ``inf`` where the ray meets nothing.
        """
        rays = self.pixel_rays(R_nc)
        rng = self.world.raycast(np.asarray(p_c, float), rays.reshape(-1, 3)).reshape(rays.shape[:2])
        if along == "axis":
            rng = rng * (rays @ np.asarray(R_nc, float)[:, 0])
        elif along != "ray":
            raise ValueError(f"along must be 'ray' or 'axis', got {along!r}")
        return rng.astype(np.float32)

    def project(self, p_c: np.ndarray, R_nc: np.ndarray, points_ned: np.ndarray,
                border_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Raw pixel positions (N, 2) of NED points (N, 3), and (N,) visibility: in front of the
        camera, inside the image (``border_px`` from the edge) and not occluded (ray cast)."""
        X = np.atleast_2d(np.asarray(points_ned, float))
        h_c = (X - np.asarray(p_c, float)) @ np.asarray(R_nc, float)
        uv_ideal = self.camera.project(h_c)
        front = h_c[:, 0] > self.options.near_m
        uv = np.full_like(uv_ideal, np.nan)
        if np.any(front):
            uv[front] = self.camera.distort(uv_ideal[front])
        visible = front & self.camera.in_image(uv, border_px)
        if np.any(visible):
            d = X[visible] - p_c
            dist = np.linalg.norm(d, axis=1)
            hit = self.world.raycast(np.asarray(p_c, float), d)
            visible[np.nonzero(visible)[0]] = hit >= dist - 1e-6 * dist - 1e-4
        return uv, visible


class _View:
    """Per-frame camera quantities shared by every surface drawn."""

    def __init__(self, cam: PinholeCamera, p_c: np.ndarray, R_nc: np.ndarray, options: RenderOptions):
        self.p_c = p_c
        self.R_nc = R_nc
        self.axis = R_nc[:, 0]  # optical axis in NED
        self.near, self.far = options.near_m, options.far_m
        self.f = math.sqrt(cam.fx * cam.fy)
        self.fx, self.fy, self.cx, self.cy = cam.fx, cam.fy, cam.cx, cam.cy
        self.M = cam.K @ PAPER_TO_OPENCV @ R_nc.T
        # Frustum sides (through the camera centre, inward normals in NED), half a pixel beyond the
        # image edge, plus the near and far planes as offsets along the optical axis.
        m = 1.0
        u0, u1, v0, v1 = -0.5 - m, cam.width - 0.5 + m, -0.5 - m, cam.height - 0.5 + m
        sides_c = [
            np.array([cam.cx - u0, cam.fx, 0.0]),
            np.array([u1 - cam.cx, -cam.fx, 0.0]),
            np.array([cam.cy - v0, 0.0, cam.fy]),
            np.array([v1 - cam.cy, 0.0, -cam.fy]),
        ]
        self.planes_n = np.column_stack([R_nc @ n for n in sides_c] + [self.axis, -self.axis])  # (3, 6)
        self.planes_d = np.array([0.0, 0.0, 0.0, 0.0, self.near, -self.far])

    def project(self, X: np.ndarray) -> np.ndarray:
        h = (X - self.p_c) @ self.M.T
        return h[:, :2] / h[:, 2:3]

    def inverse_depth(self, normal: np.ndarray, offset: float, x0: int, y0: int, w: int, h: int) -> np.ndarray:
        """1 / depth-along-axis of plane ``normal . X = offset`` over a pixel box, (h, w) float32."""
        n_c = self.R_nc.T @ normal
        D = offset - normal @ self.p_c
        a = n_c[1] / self.fx / D
        b = n_c[2] / self.fy / D
        c = (n_c[0] - n_c[1] * self.cx / self.fx - n_c[2] * self.cy / self.fy) / D
        us = (a * np.arange(x0, x0 + w) + c).astype(np.float32)
        vs = (b * np.arange(y0, y0 + h)).astype(np.float32)
        return vs[:, None] + us[None, :]
