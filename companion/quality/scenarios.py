"""The service configuration a scenario implies, and overrides of it (``--set section.key=value``).

A scenario (config/scenarios/<name>.yaml) describes the world and the circuit flown over it. The
service configuration for a flight follows from it exactly as ``companion demo`` builds it
(companion/demo.py, ``daemon_config``): the circuit's altitude, speed, clearance and waypoints, the
simulator's attitude sigmas as the navigation floors (the ArduPilot flavour sends no attitude
covariance), then the scenario's own ``service:`` settings when it carries them, then the
caller's overrides. Every value goes through the configuration's validation: a wrong key or
value is a :class:`ConfigError` naming where it came from and the dotted key.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import yaml

from companion.config import CompanionConfig, ConfigError, config_from_dict


def _merge(base: dict, extra: Mapping) -> dict:
    """Nested dict ``base`` updated by the nested mapping ``extra`` (a new dict; leaves replaced)."""
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def parse_set(expr: str) -> dict[str, Any]:
    """``"section.key=value"`` -> ``{"section": {"key": value}}``; the value is parsed as YAML
    (``-30``, ``true``, ``[[0, 0], [50, 0]]``). ConfigError on a malformed expression."""
    key, sep, text = expr.partition("=")
    parts = key.strip().split(".")
    if not sep or len(parts) < 2 or not all(parts):
        raise ConfigError(f"--set {expr!r}: expected section.key=value (e.g. camera.mount_pitch_deg=-30)")
    try:
        value = yaml.safe_load(text) if text.strip() else ""
    except yaml.YAMLError as exc:
        raise ConfigError(f"--set {expr!r}: the value is not valid YAML: {exc}") from exc
    nested: Any = value
    for part in reversed(parts):
        nested = {part: nested}
    return nested


def circuit_settings(world, scenario: str, parameterisation: str, seed: int, camera_rate_hz: float) -> dict[str, Any]:
    """The service settings the scenario's circuit implies (as the demo's ``daemon_config``)."""
    from companion.config import SimConfig

    c = world.circuit
    sim = SimConfig()
    return {
        "nav": {"attitude_sigma_floor_deg": float(sim.nav_tilt_sigma_deg), "yaw_sigma_floor_deg": float(sim.nav_yaw_sigma_deg)},
        "camera": {"source": "synthetic", "rate_hz": float(camera_rate_hz)},
        "mapper": {"parameterisation": parameterisation},
        "avoidance": {"clearance_m": float(world.clearance_m), "nominal_alt_m": float(c.altitude_agl_m)},
        "control": {"commanding_enabled": True, "cruise_speed_mps": float(c.speed_mps),
                    "waypoints_ne_m": [[float(n), float(e)] for n, e in c.waypoints_ne_m]},
        "sim": {"scenario": str(scenario), "seed": int(seed)},
    }


def flight_config(world, scenario: str, parameterisation: str, seed: int, camera_rate_hz: float,
                  overrides: tuple[tuple[str, Mapping], ...] = ()) -> CompanionConfig:
    """The validated service configuration of one flight over ``world`` (loaded from ``scenario``,
    a name or path): the circuit's settings, then the scenario's ``service:`` section (if the
    scenario schema has one), then each ``(source, nested mapping)`` of ``overrides`` in order."""
    data = circuit_settings(world, scenario, parameterisation, seed, camera_rate_hz)
    service = getattr(world, "service", None)
    layers = ((f"scenario {world.name!r} service", service),) if service else ()
    cfg = config_from_dict(data, f"scenario {world.name!r}")
    for source, extra in (*layers, *overrides):
        data = _merge(data, extra)
        cfg = config_from_dict(data, source)
    return cfg
