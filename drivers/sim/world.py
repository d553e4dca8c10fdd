"""The simulated world: ground, textured boxes (buildings, tree lines), ridges, and the circuit.

A scenario is a YAML file (``config/scenarios/<name>.yaml``) validated into frozen dataclasses
with the same machinery as the service configuration, so a mistake is a
:class:`companion.config.ConfigError` naming the file and the dotted key.

Geometry is exact and planar: every structure is a set of convex planar faces in the local NED
frame (altitude ``h = -z``, ground at altitude 0). Each face carries a texture *description*
(:class:`TextureSpec`: kind, size in texels, seed, and for buildings the window rectangles); the
renderer synthesises the pixels (``drivers/sim/textures.py``). Ground truth for tests and the demo:

* :meth:`World.terrain_height` - altitude of the top surface at (north, east), batched;
* :meth:`World.true_height_grid` - the same sampled at cell centres, for map RMSE;
* :meth:`World.raycast` - exact range along rays against the ground plane and every face;
* :attr:`World.obstacles` - footprints, heights and the height up to which they carry texture;
* :meth:`World.window_corners_ned` - the 3D corners of every window (known Harris corners).

Why the texture stops below the roof: in the seed paper's simulation (section IV) the building's
texture ended at the windows, about 30 ft up a 40 ft building, and the map showed about 30 ft.
``textured_height_m`` reproduces that: windows only below it, plain wall above, plain roof.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import yaml

import drivers
from companion.config import CompanionConfig, ConfigError, _build, _f

SCENARIO_DIR = Path(drivers.__file__).resolve().parents[1] / "config" / "scenarios"

UP = np.array([0.0, 0.0, -1.0])  # NED
DOWN = np.array([0.0, 0.0, 1.0])

# --------------------------------------------------------------------------------------------
# Scenario schema (YAML -> frozen dataclasses)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class HomeSpec:
    """Geodetic position of the local NED origin (ground level), for GLOBAL_POSITION_INT / GPS_GLOBAL_ORIGIN."""

    lat_deg: float = _f(47.397742, "deg", -90.0, 90.0)
    lon_deg: float = _f(8.545594, "deg", -180.0, 180.0)
    alt_m: float = _f(488.0, "m", -500.0, 9000.0, "AMSL altitude of the origin (the ground)")


@dataclass(frozen=True, slots=True)
class GroundSpec:
    """The ground: a textured plane at altitude 0, tiled with period ``tile_px * texel_m``."""

    texture: Literal["fields", "plain"] = _f("fields", doc="fields: patches, field boundaries and rocks (corner rich)")
    texel_m: float = _f(0.05, "m", 0.005, 1.0)
    tile_px: int = _f(4096, "px", 256, 8192, "texture tile edge; a multiple of 64")


@dataclass(frozen=True, slots=True)
class BoxSpec:
    """A box standing on the ground: a building (windows) or anything block-shaped."""

    name: str = _f("box")
    center_ne_m: tuple[float, float] = _f((0.0, 0.0), "m")
    size_m: tuple[float, float] = _f((10.0, 10.0), "m", 0.1, 1e4, "length along the yaw axis, width across")
    height_m: float = _f(10.0, "m", 0.1, 1000.0)
    yaw_deg: float = _f(0.0, "deg", -360.0, 360.0, "direction of the length axis, clockwise from north")
    wall_texture: Literal["windows", "plain", "leaves", "fields"] = _f("windows")
    textured_height_m: float | None = _f(None, "m", 0.0, 1000.0, "windows only below this altitude; default: the full height")
    roof_texture: Literal["plain", "gravel", "leaves", "fields"] = _f("plain")
    texel_m: float = _f(0.025, "m", 0.002, 1.0)
    window_width_m: float = _f(1.2, "m", 0.1, 100.0)
    window_height_m: float = _f(1.6, "m", 0.1, 100.0)
    floor_height_m: float = _f(3.0, "m", 0.5, 100.0)
    bay_width_m: float = _f(2.5, "m", 0.2, 100.0, "horizontal spacing of windows")
    sill_m: float = _f(0.9, "m", 0.0, 100.0, "window bottom above each floor")
    contrast: float = _f(1.0, "", 0.02, 1.0, "texture contrast of walls and roof about their mean grey (1 = as drawn; "
                                              "lower = fainter, fewer Harris corners)")


@dataclass(frozen=True, slots=True)
class TreeLineSpec:
    """A line of trees: a box from ``start_ne_m`` to ``end_ne_m`` with a leafy texture on every face."""

    name: str = _f("trees")
    start_ne_m: tuple[float, float] = _f((0.0, 0.0), "m")
    end_ne_m: tuple[float, float] = _f((10.0, 0.0), "m")
    depth_m: float = _f(6.0, "m", 0.1, 1000.0, "thickness across the line")
    height_m: float = _f(6.0, "m", 0.1, 1000.0)
    texel_m: float = _f(0.04, "m", 0.002, 1.0)
    contrast: float = _f(1.0, "", 0.02, 1.0, "leaf texture contrast about its mean grey (1 = as drawn; lower = fainter)")


@dataclass(frozen=True, slots=True)
class RidgeSpec:
    """A ridge: profile ``h cos(pi c / w)`` across its axis (concave), approximated by planar facets."""

    name: str = _f("ridge")
    start_ne_m: tuple[float, float] = _f((0.0, 0.0), "m", doc="one end of the crest line")
    end_ne_m: tuple[float, float] = _f((50.0, 0.0), "m")
    width_m: float = _f(30.0, "m", 0.5, 1e4, "base width across the axis")
    height_m: float = _f(4.0, "m", 0.1, 1000.0)
    facets: int = _f(6, "", 2, 64, "planar facets across the profile")
    texel_m: float = _f(0.05, "m", 0.005, 1.0)


@dataclass(frozen=True, slots=True)
class CircuitSpec:
    """The closed route the vehicle flies (seed 000, section IV: ~50 ft AGL, 20 ft/s, 50 ft clearance)."""

    waypoints_ne_m: tuple[tuple[float, float], ...] = _f(((0.0, 0.0), (200.0, 0.0), (200.0, 60.0), (0.0, 60.0)), "m")
    altitude_agl_m: float = _f(15.0, "m", 1.0, 1000.0, "nominal height above the ground (altitude 0)")
    speed_mps: float = _f(6.0, "m/s", 0.1, 50.0)
    clearance_m: float = _f(15.0, "m", 0.0, 1000.0, "h_c of the avoidance law")


@dataclass(frozen=True, slots=True)
class ScenarioSpec:
    name: str = _f("unnamed")
    description: str = _f("")
    seed: int = _f(1, "", 0, 2**31 - 1, "textures are a deterministic function of this")
    sun_azimuth_deg: float = _f(210.0, "deg", -360.0, 360.0, "direction the light comes from, clockwise from north")
    sun_elevation_deg: float = _f(50.0, "deg", 1.0, 90.0)
    ambient: float = _f(0.45, "", 0.0, 1.0, "fraction of the brightness that does not depend on the sun")
    home: HomeSpec = HomeSpec()
    ground: GroundSpec = GroundSpec()
    boxes: tuple[BoxSpec, ...] = _f(())
    tree_lines: tuple[TreeLineSpec, ...] = _f(())
    ridges: tuple[RidgeSpec, ...] = _f(())
    circuit: CircuitSpec = CircuitSpec()


# --------------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TextureSpec:
    """What a face looks like; ``drivers.sim.textures.synthesize`` turns it into pixels.

    kind: "fields", "windows", "plain", "gravel", "leaves", or "ground" (the ground tile itself,
        draped over a sloping face; ``shade`` then applies when drawing).
    width_px, height_px: texture size; texel (col, row) covers the face's texel grid cell.
    texel_m: nominal texel size (m).
    seed: deterministic per face.
    shade: brightness factor from the sun (Lambert + ambient), baked into the texels.
    windows: (K, 4) int texel rectangles [col0, row0, col1, row1) drawn dark on the wall.
    wrap: the texture tiles the plane (ground).
    contrast: the texels' spread about their mean grey is scaled by this (1 = as drawn).
    """

    kind: str
    width_px: int
    height_px: int
    texel_m: float
    seed: int
    shade: float = 1.0
    windows: np.ndarray = None  # type: ignore[assignment]
    wrap: bool = False
    contrast: float = 1.0


@dataclass(frozen=True, slots=True)
class Face:
    """A convex planar polygon of a structure with its texture mapping.

    vertices_ned: (M, 3), counter-clockwise seen from outside (around ``normal_ned``).
    normal_ned: (3,) outward unit normal; the plane is ``normal . X = offset``.
    origin_ned: (3,) 3D position of the centre of texel (0, 0).
    axis_u_ned, axis_v_ned: (3,) 3D step of one texel along columns / rows, so texel (col, row)
        is at ``origin + col * axis_u + row * axis_v``.
    """

    structure: str
    vertices_ned: np.ndarray
    normal_ned: np.ndarray
    offset: float
    origin_ned: np.ndarray
    axis_u_ned: np.ndarray
    axis_v_ned: np.ndarray
    texture: TextureSpec


@dataclass(frozen=True, slots=True)
class Obstacle:
    """Ground truth of one structure.

    kind: "building" (box), "trees" or "ridge". footprint_ne_m: (K, 2) polygon (north, east).
    height_m: top altitude. textured_height_m: altitude up to which the structure carries texture a
    monocular mapper can track (windows stop below the roof; a plain box has none; leaves, fields
    and gravel cover everything).
    """

    name: str
    kind: str
    footprint_ne_m: np.ndarray
    height_m: float
    textured_height_m: float


def _face(structure: str, vertices: np.ndarray, outward: np.ndarray, origin: np.ndarray,
          axis_u: np.ndarray, axis_v: np.ndarray, texture: TextureSpec) -> Face:
    """Build a face; orders the vertices counter-clockwise around the outward normal."""
    vertices = np.asarray(vertices, float)
    # Newell's normal: robust when leading vertices are nearly collinear (ridge end caps).
    normal = np.cross(vertices, np.roll(vertices, -1, axis=0)).sum(axis=0)
    normal = normal / np.linalg.norm(normal)
    if normal @ outward < 0:
        vertices = vertices[::-1].copy()
        normal = -normal
    return Face(structure, vertices, normal, float(normal @ vertices[0]), np.asarray(origin, float),
                np.asarray(axis_u, float), np.asarray(axis_v, float), texture)


def _ned(ne: np.ndarray, alt: float | np.ndarray) -> np.ndarray:
    ne = np.asarray(ne, float)
    alt = np.broadcast_to(np.asarray(alt, float), ne.shape[:-1])
    return np.concatenate([ne, -alt[..., None]], axis=-1)


def _lambert(normal: np.ndarray, sun_from: np.ndarray, ambient: float) -> float:
    """Brightness of a face: ambient plus diffuse, normalised so that flat ground has 1."""
    ground = ambient + (1 - ambient) * max(0.0, float(UP @ sun_from))
    return (ambient + (1 - ambient) * max(0.0, float(normal @ sun_from))) / ground


class _Box:
    """Oriented box on the ground: centre (N, E), unit axes ``u`` (length) and ``v`` (width)."""

    def __init__(self, name: str, kind: str, center: np.ndarray, yaw_rad: float, length: float, width: float,
                 height: float, textured_height: float):
        self.name, self.kind = name, kind
        self.center = np.asarray(center, float)
        self.u = np.array([math.cos(yaw_rad), math.sin(yaw_rad)])
        self.v = np.array([-math.sin(yaw_rad), math.cos(yaw_rad)])
        self.half = np.array([length / 2, width / 2])
        self.height = height
        self.textured_height = textured_height

    def footprint(self) -> np.ndarray:
        """(4, 2) footprint corners (north, east), in order around the box."""
        c, u, v = self.center, self.u * self.half[0], self.v * self.half[1]
        return np.array([c - u - v, c + u - v, c + u + v, c - u + v])

    def top_height(self, north: np.ndarray, east: np.ndarray) -> np.ndarray:
        d0, d1 = north - self.center[0], east - self.center[1]
        a = d0 * self.u[0] + d1 * self.u[1]
        c = d0 * self.v[0] + d1 * self.v[1]
        inside = (np.abs(a) <= self.half[0]) & (np.abs(c) <= self.half[1])
        return np.where(inside, self.height, -np.inf)


class _Ridge:
    """Crest from ``a`` to ``b`` (N, E); profile heights ``h_k`` at across-offsets ``c_k``."""

    def __init__(self, spec: RidgeSpec):
        self.name = spec.name
        self.a = np.asarray(spec.start_ne_m, float)
        self.b = np.asarray(spec.end_ne_m, float)
        self.length = float(np.linalg.norm(self.b - self.a))
        self.u = (self.b - self.a) / self.length
        self.v = np.array([-self.u[1], self.u[0]])
        self.width, self.height = spec.width_m, spec.height_m
        self.c = np.linspace(-spec.width_m / 2, spec.width_m / 2, spec.facets + 1)
        self.h = spec.height_m * np.cos(np.pi * self.c / spec.width_m)
        self.h[0] = self.h[-1] = 0.0

    def footprint(self) -> np.ndarray:
        w = self.v * self.width / 2
        return np.array([self.a - w, self.b - w, self.b + w, self.a + w])

    def top_height(self, north: np.ndarray, east: np.ndarray) -> np.ndarray:
        d0, d1 = north - self.a[0], east - self.a[1]
        along = d0 * self.u[0] + d1 * self.u[1]
        across = d0 * self.v[0] + d1 * self.v[1]
        inside = (along >= 0) & (along <= self.length) & (np.abs(across) <= self.width / 2)
        return np.where(inside, np.interp(across, self.c, self.h), -np.inf)


def window_rectangles(wall_length_m: float, spec: BoxSpec, textured_height_m: float,
                      building_height_m: float, cols: int, rows: int) -> np.ndarray:
    """Window layout of one wall in texels: (K, 4) ``[col0, row0, col1, row1)``, row 0 at the roof.

    Windows sit in bays of ``bay_width_m`` centred on the wall and on floors of
    ``floor_height_m``; a window exists only when its top is at or below ``textured_height_m``.
    Edges are snapped to the texel grid so their 3D corners are exact.
    """
    su, sv = wall_length_m / cols, building_height_m / rows
    n_bays = int((wall_length_m - 0.5) // spec.bay_width_m)
    n_floors = int(building_height_m // spec.floor_height_m) + 1
    rects = []
    start = (wall_length_m - n_bays * spec.bay_width_m) / 2
    for floor in range(n_floors):
        bottom = floor * spec.floor_height_m + spec.sill_m
        top = bottom + spec.window_height_m
        if top > textured_height_m + 1e-9 or top > building_height_m:
            continue
        r0 = round((building_height_m - top) / sv)
        r1 = round((building_height_m - bottom) / sv)
        for bay in range(n_bays):
            centre = start + (bay + 0.5) * spec.bay_width_m
            c0 = round((centre - spec.window_width_m / 2) / su)
            c1 = round((centre + spec.window_width_m / 2) / su)
            if c0 >= 1 and c1 <= cols - 1 and r0 >= 1 and r1 > r0:
                rects.append((c0, r0, c1, r1))
    return np.array(rects, dtype=np.int64).reshape(-1, 4)


# --------------------------------------------------------------------------------------------
# The world
# --------------------------------------------------------------------------------------------


class World:
    """A validated scenario with exact geometry and ground truth. Build with :meth:`load`."""

    def __init__(self, spec: ScenarioSpec, source: str = "<dict>", service: dict | None = None):
        self.spec = spec
        self.source = source
        # The service settings the scenario carries (a partial companion configuration, validated).
        self.service: dict = dict(service or {})
        self._check(spec, source)
        sun_az, sun_el = math.radians(spec.sun_azimuth_deg), math.radians(spec.sun_elevation_deg)
        # Unit vector from the scene towards the sun (NED).
        self.sun_from = np.array([math.cos(sun_el) * math.cos(sun_az), math.cos(sun_el) * math.sin(sun_az), -math.sin(sun_el)])
        self._faces: list[Face] = []
        self._boxes: list[_Box] = []
        self._ridges: list[_Ridge] = []
        self._windows: list[tuple[str, np.ndarray]] = []  # (structure, (K, 4, 3) corners)
        obstacles: list[Obstacle] = []
        for box in spec.boxes:
            b, textured = self._add_box(box)
            obstacles.append(Obstacle(box.name, "building", b.footprint(), box.height_m, textured))
        for line in spec.tree_lines:
            b = self._add_tree_line(line)
            obstacles.append(Obstacle(line.name, "trees", b.footprint(), line.height_m, line.height_m))
        for ridge in spec.ridges:
            r = self._add_ridge(ridge)
            obstacles.append(Obstacle(ridge.name, "ridge", r.footprint(), ridge.height_m, ridge.height_m))
        self.faces: tuple[Face, ...] = tuple(self._faces)
        self.obstacles: tuple[Obstacle, ...] = tuple(obstacles)
        self._prepare_raycast()

    # ---- loading ------------------------------------------------------------------------------

    @classmethod
    def load(cls, name_or_path: str | Path, seed: int | None = None) -> "World":
        """Load a scenario: a path to a YAML file, or a bare name in ``config/scenarios/``.

        ``seed`` overrides the scenario's texture seed.
        """
        text = str(name_or_path)
        path = Path(text)
        if not (path.suffix in (".yaml", ".yml") or path.exists() or "/" in text):
            path = SCENARIO_DIR / f"{text}.yaml"
            if not path.is_file():
                known = ", ".join(sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))) or "none"
                raise ConfigError(f"{path}: no scenario named {text!r} (known: {known})")
        try:
            data = yaml.safe_load(path.read_text())
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read scenario: {exc.strerror or exc}") from exc
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
        return cls.from_dict(data, str(path), seed=seed)

    @classmethod
    def from_dict(cls, data: dict | None, where: str = "<dict>", seed: int | None = None) -> "World":
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(f"{where}: a scenario must be a mapping of keys")
        data = dict(data)
        service = data.pop("service", None) or {}
        if not isinstance(service, dict):
            raise ConfigError(f"{where}: 'service' must be a mapping of configuration sections, got {type(service).__name__}")
        _build(CompanionConfig, service, "service", where)  # validated like `companion run`'s configuration
        spec = _build(ScenarioSpec, data, "", where)
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**31:
                raise ConfigError(f"{where}: seed override must be an integer in [0, 2^31), got {seed!r}")
            spec = dataclasses.replace(spec, seed=seed)
        return cls(spec, where, service)

    @staticmethod
    def _check(spec: ScenarioSpec, where: str) -> None:
        """Cross-field checks the per-key validation cannot make."""
        for i, box in enumerate(spec.boxes):
            if box.textured_height_m is not None and box.textured_height_m > box.height_m:
                raise ConfigError(f"{where}: 'boxes[{i}].textured_height_m' = {box.textured_height_m} is above "
                                  f"'boxes[{i}].height_m' = {box.height_m}")
        for key, items in (("tree_lines", spec.tree_lines), ("ridges", spec.ridges)):
            for i, item in enumerate(items):
                if np.hypot(*np.subtract(item.end_ne_m, item.start_ne_m)) < 0.1:
                    raise ConfigError(f"{where}: '{key}[{i}].end_ne_m' must be at least 0.1 m from 'start_ne_m'")
        wps = np.asarray(spec.circuit.waypoints_ne_m, float).reshape(-1, 2)
        if len(wps) < 2:
            raise ConfigError(f"{where}: 'circuit.waypoints_ne_m' needs at least 2 waypoints, got {len(wps)}")
        legs = np.linalg.norm(np.diff(np.vstack([wps, wps[:1]]), axis=0), axis=1)
        if np.any(legs < 0.1):
            raise ConfigError(f"{where}: 'circuit.waypoints_ne_m' has repeated waypoints (legs shorter than 0.1 m)")
        names = [o.name for o in (*spec.boxes, *spec.tree_lines, *spec.ridges)]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ConfigError(f"{where}: structure names must be unique, repeated: {', '.join(dup)}")
        if spec.ground.tile_px % 64:
            raise ConfigError(f"{where}: 'ground.tile_px' = {spec.ground.tile_px} must be a multiple of 64")

    # ---- scenario facts -------------------------------------------------------------------------

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def seed(self) -> int:
        return self.spec.seed

    @property
    def home(self) -> HomeSpec:
        return self.spec.home

    @property
    def ground(self) -> GroundSpec:
        return self.spec.ground

    @property
    def circuit(self) -> CircuitSpec:
        return self.spec.circuit

    @property
    def clearance_m(self) -> float:
        return self.spec.circuit.clearance_m

    @property
    def waypoints_ne_m(self) -> np.ndarray:
        """(K, 2) circuit waypoints (north, east); the route closes back to the first."""
        return np.asarray(self.spec.circuit.waypoints_ne_m, float).reshape(-1, 2)

    @property
    def ground_texture(self) -> TextureSpec:
        """The ground's texture tile (kind "ground" for draped faces is this same tile). It wraps: the
        pattern repeats every ``tile_px * texel_m`` metres north and east."""
        g = self.spec.ground
        seed = int(np.random.SeedSequence([self.spec.seed, 1_000_003]).generate_state(1)[0])
        return TextureSpec(g.texture, g.tile_px, g.tile_px, g.texel_m, seed, 1.0, None, wrap=True)

    @property
    def ground_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """NED step of one ground texel along texture columns (east) and rows (north)."""
        s = self.spec.ground.texel_m
        return np.array([0.0, s, 0.0]), np.array([s, 0.0, 0.0])

    @property
    def ground_period_m(self) -> float:
        return self.spec.ground.tile_px * self.spec.ground.texel_m

    def ground_tile_origin(self, ne: np.ndarray) -> np.ndarray:
        """NED centre of texel (0, 0) of the ground tile that contains ``ne`` (north, east)."""
        period = self.ground_period_m
        u, v = self.ground_axes
        corner = np.array([math.floor(ne[0] / period) * period, math.floor(ne[1] / period) * period, 0.0])
        return corner + 0.5 * (u + v)

    def obstacle(self, name: str) -> Obstacle:
        for o in self.obstacles:
            if o.name == name:
                return o
        raise KeyError(f"no structure named {name!r} in scenario {self.name!r}")

    # ---- building the faces ---------------------------------------------------------------------

    def _seed(self, *parts: int) -> int:
        return int(np.random.SeedSequence([self.spec.seed, len(self._faces), *parts]).generate_state(1)[0])

    def _add_prism_walls(self, name: str, base: np.ndarray, height: float, texel: float, kind: str,
                         window_layout=None, contrast: float = 1.0) -> None:
        """Vertical walls over a convex footprint ``base`` (K, 2) from altitude 0 to ``height``."""
        centre = base.mean(axis=0)
        for k in range(len(base)):
            p, q = base[k], base[(k + 1) % len(base)]
            mid = (p + q) / 2
            outward = _ned(mid - centre, 0.0)
            outward[2] = 0.0
            outward /= np.linalg.norm(outward)
            right = np.cross(outward, DOWN)  # what a viewer facing the wall sees as "right"
            if _ned(q - p, 0.0) @ right < 0:
                p, q = q, p
            length = float(np.linalg.norm(q - p))
            cols = max(2, round(length / texel))
            rows = max(2, round(height / texel))
            top_left = _ned(p, height)
            axis_u = (_ned(q, height) - top_left) / cols
            axis_v = DOWN * (height / rows)
            windows = window_layout(length, cols, rows) if window_layout else None
            if windows is not None and len(windows):
                self._windows.append((name, _texel_rect_corners(top_left, axis_u, axis_v, windows)))
            tex = TextureSpec(kind, cols, rows, texel, self._seed(k), _lambert(outward, self.sun_from, self.spec.ambient),
                              windows, contrast=contrast)
            verts = np.array([_ned(p, height), _ned(q, height), _ned(q, 0.0), _ned(p, 0.0)])
            self._faces.append(_face(name, verts, outward, top_left + 0.5 * (axis_u + axis_v), axis_u, axis_v, tex))

    def _add_roof(self, name: str, b: _Box, kind: str, texel: float, contrast: float = 1.0) -> None:
        corners = b.footprint()
        length, width = 2 * b.half
        cols, rows = max(2, round(length / texel)), max(2, round(width / texel))
        o = _ned(corners[0], b.height)
        axis_u = _ned(b.u * length / cols, 0.0)
        axis_v = _ned(b.v * width / rows, 0.0)
        tex = TextureSpec(kind, cols, rows, texel, self._seed(99), _lambert(UP, self.sun_from, self.spec.ambient),
                          contrast=contrast)
        self._faces.append(_face(name, _ned(corners, b.height), UP, o + 0.5 * (axis_u + axis_v), axis_u, axis_v, tex))

    def _add_box(self, spec: BoxSpec) -> tuple[_Box, float]:
        textured = spec.height_m if spec.textured_height_m is None else spec.textured_height_m
        b = _Box(spec.name, "building", spec.center_ne_m, math.radians(spec.yaw_deg), spec.size_m[0], spec.size_m[1],
                 spec.height_m, textured)
        self._boxes.append(b)
        layout = None
        if spec.wall_texture == "windows":
            def layout(length, cols, rows):
                return window_rectangles(length, spec, textured, spec.height_m, cols, rows)
        self._add_prism_walls(spec.name, b.footprint(), spec.height_m, spec.texel_m, spec.wall_texture, layout, spec.contrast)
        self._add_roof(spec.name, b, spec.roof_texture, spec.texel_m, spec.contrast)
        has_windows = any(owner == spec.name for owner, _ in self._windows)
        if spec.roof_texture != "plain":
            trackable = spec.height_m
        elif spec.wall_texture == "windows":
            trackable = textured if has_windows else 0.0
        elif spec.wall_texture == "plain":
            trackable = 0.0
        else:
            trackable = spec.height_m
        return b, trackable

    def _add_tree_line(self, spec: TreeLineSpec) -> _Box:
        a, e = np.asarray(spec.start_ne_m, float), np.asarray(spec.end_ne_m, float)
        d = e - a
        b = _Box(spec.name, "trees", (a + e) / 2, math.atan2(d[1], d[0]), float(np.linalg.norm(d)), spec.depth_m,
                 spec.height_m, spec.height_m)
        self._boxes.append(b)
        self._add_prism_walls(spec.name, b.footprint(), spec.height_m, spec.texel_m, "leaves", contrast=spec.contrast)
        self._add_roof(spec.name, b, "leaves", spec.texel_m, spec.contrast)
        return b

    def _add_ridge(self, spec: RidgeSpec) -> _Ridge:
        r = _Ridge(spec)
        self._ridges.append(r)
        s = spec.texel_m
        ambient = self.spec.ambient
        # Facets: quads between consecutive profile points, running the length of the crest. The
        # ground texture is draped over them (vertical projection: still an affine texel -> plane
        # map, so still a homography), so the ridge continues the ground without seams.
        ground_u, ground_v = self.ground_axes
        for k in range(spec.facets):
            p0 = _ned(r.a + r.v * r.c[k], r.h[k])
            p1 = _ned(r.a + r.v * r.c[k + 1], r.h[k + 1])
            q0, q1 = p0 + _ned(r.b - r.a, 0.0), p1 + _ned(r.b - r.a, 0.0)
            outward = np.cross(q0 - p0, p1 - p0)
            outward = outward if outward @ UP > 0 else -outward
            outward /= np.linalg.norm(outward)
            offset = outward @ p0

            def drape(x: np.ndarray) -> np.ndarray:
                """Lift a ground point (z = 0) vertically onto the facet plane."""
                return np.array([x[0], x[1], (offset - outward[0] * x[0] - outward[1] * x[1]) / outward[2]])

            origin = drape(self.ground_tile_origin(p0[:2]))
            axis_u, axis_v = drape(origin + ground_u) - origin, drape(origin + ground_v) - origin
            tex = dataclasses.replace(self.ground_texture, kind="ground", shade=_lambert(outward, self.sun_from, ambient))
            self._faces.append(_face(spec.name, np.array([p0, q0, q1, p1]), outward, origin, axis_u, axis_v, tex))
        # End caps: vertical convex polygons under the profile.
        for end, outward_ne in ((r.a, -r.u), (r.b, r.u)):
            outward = _ned(outward_ne, 0.0)
            right = np.cross(outward, DOWN)
            side = 1.0 if _ned(r.v, 0.0) @ right > 0 else -1.0
            verts = _ned(end + np.outer(r.c, r.v), r.h)
            cols, rows = max(2, round(spec.width_m / s)), max(2, round(spec.height_m / s))
            top_left = _ned(end - side * r.v * spec.width_m / 2, spec.height_m)
            axis_u = _ned(side * r.v * spec.width_m / cols, 0.0)
            axis_v = DOWN * (spec.height_m / rows)
            tex = TextureSpec("fields", cols, rows, s, self._seed(50), _lambert(outward, self.sun_from, ambient))
            self._faces.append(_face(spec.name, verts, outward, top_left + 0.5 * (axis_u + axis_v), axis_u, axis_v, tex))
        return r

    # ---- ground truth ---------------------------------------------------------------------------

    def terrain_height(self, north, east, textured_only: bool = False) -> np.ndarray:
        """Altitude (m, up) of the top surface at (north, east): max over structures, ground 0.

        Arrays of any (broadcastable) shape; the result has their broadcast shape.
        ``textured_only``: cap each structure at its ``textured_height_m`` (what a mapper that needs
        texture can see; the seed paper's map of its building stopped at the windows).
        """
        north, east = np.broadcast_arrays(np.asarray(north, float), np.asarray(east, float))
        h = np.zeros(north.shape)
        for b in self._boxes:
            top = b.top_height(north, east)
            if textured_only:
                top = np.minimum(top, self._trackable(b.name))
            h = np.maximum(h, top)
        for r in self._ridges:
            h = np.maximum(h, r.top_height(north, east))
        return h

    def _trackable(self, name: str) -> float:
        return self.obstacle(name).textured_height_m

    def true_height_grid(self, x0: float, y0: float, x1: float, y1: float, cell: float,
                         textured_only: bool = False) -> np.ndarray:
        """Terrain altitude sampled at cell centres, for map RMSE.

        Cells ``[x0 + i cell, x0 + (i+1) cell) x [y0 + j cell, ...)`` (x north, y east) for
        ``i < ceil((x1 - x0) / cell)``; returns ``(n_north, n_east)`` altitudes at
        ``(x0 + (i + 0.5) cell, y0 + (j + 0.5) cell)``.
        """
        if not cell > 0 or not x1 > x0 or not y1 > y0:
            raise ValueError(f"need cell > 0, x1 > x0 and y1 > y0; got cell={cell}, x=({x0}, {x1}), y=({y0}, {y1})")
        nx, ny = math.ceil((x1 - x0) / cell - 1e-9), math.ceil((y1 - y0) / cell - 1e-9)
        xs = x0 + (np.arange(nx) + 0.5) * cell
        ys = y0 + (np.arange(ny) + 0.5) * cell
        return self.terrain_height(xs[:, None], ys[None, :], textured_only)

    def window_corners_ned(self, structure: str | None = None) -> np.ndarray:
        """(N, 3) NED corners of every window (4 per window), or of one structure's windows."""
        rows = [corners for owner, corners in self._windows if structure is None or owner == structure]
        return np.concatenate(rows).reshape(-1, 3) if rows else np.zeros((0, 3))

    # ---- ray casting ----------------------------------------------------------------------------

    def _prepare_raycast(self) -> None:
        """Per face: an in-plane basis and the 2D polygon, for the point-in-polygon test."""
        self._ray_faces = []
        for f in self.faces:
            e1 = f.vertices_ned[1] - f.vertices_ned[0]
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(f.normal_ned, e1)
            poly = (f.vertices_ned - f.vertices_ned[0]) @ np.column_stack([e1, e2])
            edges = np.roll(poly, -1, axis=0) - poly
            self._ray_faces.append((f.normal_ned, f.offset, f.vertices_ned[0], e1, e2, poly, edges))
        # Faces grouped by structure with a bounding sphere, to skip rays that pass far away.
        self._ray_groups = []
        for name in dict.fromkeys(f.structure for f in self.faces):
            index = [k for k, f in enumerate(self.faces) if f.structure == name]
            pts = np.vstack([self.faces[k].vertices_ned for k in index])
            centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
            radius = float(np.linalg.norm(pts - centre, axis=1).max()) * (1 + 1e-9) + 1e-6
            self._ray_groups.append((centre, radius, index))

    def raycast(self, origins: np.ndarray, rays: np.ndarray, return_face: bool = False):
        """Exact range (m) along each ray to the first surface (ground plane or a face).

        origins: (3,) or (N, 3) NED; rays: (N, 3) directions (normalised here).
        Returns (N,) ranges, ``inf`` where the ray escapes; with ``return_face`` also (N,) indices
        into :attr:`faces` (-1 = ground, -2 = nothing).
        """
        rays = np.atleast_2d(np.asarray(rays, float))
        norm = np.linalg.norm(rays, axis=1, keepdims=True)
        if rays.shape[1] != 3 or np.any(norm == 0) or not np.all(np.isfinite(rays)):
            raise ValueError("rays must be (N, 3), finite and non-zero")
        d = rays / norm
        origins = np.asarray(origins, float)
        single = origins.ndim == 1
        if origins.shape[-1] != 3 or not (single or origins.shape == d.shape) or not np.all(np.isfinite(origins)):
            raise ValueError("origins must be finite, (3,) or (N, 3) like rays")
        o = origins
        best = np.full(len(d), np.inf)
        which = np.full(len(d), -2, dtype=np.int64)
        # Ground plane z = 0 (seen from above: origin z < 0, ray going down).
        oz = np.broadcast_to(o[..., 2], best.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where((d[:, 2] > 0) & (oz < 0), -oz / d[:, 2], np.inf)
        hit = t < best
        best[hit], which[hit] = t[hit], -1
        eps = 1e-9
        for centre, radius, faces in self._ray_groups:
            # Only rays passing through the structure's bounding sphere can hit its faces.
            oc = centre - o
            along = d @ oc if single else np.einsum("ij,ij->i", d, oc)
            miss2 = (oc @ oc if single else np.einsum("ij,ij->i", oc, oc)) - along**2
            sel = np.nonzero((miss2 <= radius**2) & (along > -radius))[0]
            if not len(sel):
                continue
            ds = d[sel]
            os_ = o if single else o[sel]
            for index in faces:
                n, off, v0, e1, e2, poly, edges = self._ray_faces[index]
                denom = ds @ n
                with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                    t = (off - os_ @ n) / denom
                cand = np.nonzero((np.abs(denom) > 1e-12) & (t > eps) & (t < best[sel]))[0]
                if not len(cand):
                    continue
                p = (os_ if single else os_[cand]) + t[cand, None] * ds[cand] - v0
                p2 = np.stack([p @ e1, p @ e2], axis=1)
                rel = p2[:, None, :] - poly[None, :, :]
                cross = edges[None, :, 0] * rel[:, :, 1] - edges[None, :, 1] * rel[:, :, 0]
                inside = np.all(cross >= -1e-9, axis=1)
                idx = sel[cand[inside]]
                best[idx], which[idx] = t[cand[inside]], index
        return (best, which) if return_face else best


def _texel_rect_corners(top_left: np.ndarray, axis_u: np.ndarray, axis_v: np.ndarray, rects: np.ndarray) -> np.ndarray:
    """3D corners (K, 4, 3) of texel rectangles ``[c0, r0, c1, r1)``: the edges of the texel cells."""
    c0, r0, c1, r1 = (rects[:, i, None].astype(float) for i in range(4))
    cols = np.hstack([c0, c1, c1, c0])
    rows = np.hstack([r0, r0, r1, r1])
    return top_left + cols[..., None] * axis_u + rows[..., None] * axis_v


