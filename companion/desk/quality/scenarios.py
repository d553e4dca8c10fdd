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

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
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
    return config_from_dict(merge_layers(data, (*layers, *overrides)), f"scenario {world.name!r}")


def override_layers(config_file: str | None, sets: Sequence[str] | None) -> tuple[tuple[str, dict], ...]:
    """``--config FILE`` (a partial configuration, YAML) then each ``--set section.key=value``, in
    order, as ``(source, nested mapping)`` layers for :func:`flight_config` / :func:`merge_layers`."""
    layers: list[tuple[str, dict]] = []
    if config_file:
        path = Path(config_file)
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read configuration: {exc.strerror or exc}") from exc
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: the top level must be a mapping of sections")
        layers.append((str(path), data))
    for expr in sets or ():
        layers.append((f"--set {expr}", parse_set(expr)))
    return tuple(layers)


def merge_layers(data: dict, layers: Sequence[tuple[str, Mapping]]) -> dict:
    """``data`` (a configuration as a nested dict) with each layer merged over it in order, each
    step validated (ConfigError naming the layer's source and the dotted key)."""
    for source, extra in layers:
        data = _merge(data, extra)
        config_from_dict(data, source)
    return data


def world_for(world, cfg: CompanionConfig):
    """``world`` with its circuit's altitude, speed, clearance and route taken from ``cfg`` (after
    overrides), so that figures judged against the circuit use what the service was told."""
    from drivers.sim.world import World

    c = dataclasses.replace(world.spec.circuit, altitude_agl_m=cfg.avoidance.nominal_alt_m,
                            speed_mps=cfg.control.cruise_speed_mps, clearance_m=cfg.avoidance.clearance_m,
                            waypoints_ne_m=tuple(tuple(w) for w in cfg.control.waypoints_ne_m))
    return World(dataclasses.replace(world.spec, circuit=c), world.source, world.service)
