"""Configuration: defaults documented, wrong keys/types/ranges rejected with the key and file named."""

from pathlib import Path

import pytest
import yaml

from companion.config import CompanionConfig, ConfigError, config_from_dict, describe, load_config, replace
from companion.config_cli import defaults_yaml

ROOT = Path(__file__).resolve().parents[1]


def test_default_yaml_is_current_and_documents_every_key():
    text = (ROOT / "config" / "default.yaml").read_text()
    assert text == defaults_yaml(), "config/default.yaml is stale: regenerate with `companion config --defaults`"
    for key, _default, _unit, _doc in describe():
        leaf = key.split(".")[-1]
        line = next(l for l in text.splitlines() if l.strip().startswith(f"{leaf}:"))
        assert "# [" in line, f"{key} has no unit comment"
    assert load_config(ROOT / "config" / "default.yaml") == CompanionConfig()


def test_every_shipped_config_file_loads():
    files = sorted((ROOT / "config").glob("*.yaml"))
    assert files
    for f in files:
        load_config(f)


def test_unknown_key_names_key_and_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("mapper:\n  max_feature: 50\n")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert "mapper.max_feature" in str(e.value) and str(p) in str(e.value)


def test_unknown_section(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("mappr: {}\n")
    with pytest.raises(ConfigError, match="'mappr'"):
        load_config(p)


@pytest.mark.parametrize(
    "doc, key",
    [
        ({"mapper": {"max_features": "fifty"}}, "mapper.max_features"),
        ({"mapper": {"max_features": 0}}, "mapper.max_features"),
        ({"mapper": {"max_features": 2.5}}, "mapper.max_features"),
        ({"avoidance": {"clearance_m": -1}}, "avoidance.clearance_m"),
        ({"avoidance": {"accel_mps2": float("nan")}}, "avoidance.accel_mps2"),
        ({"control": {"commanding_enabled": "yes"}}, "control.commanding_enabled"),
        ({"mapper": {"parameterisation": "polar"}}, "mapper.parameterisation"),
        ({"camera": {"mount_offset_m": 3}}, "camera.mount_offset_m"),
        ({"camera": {"mount_offset_m": [0, "a", 0]}}, "camera.mount_offset_m[1]"),
        ({"control": {"waypoints_ne_m": [[0, 0, 0]]}}, "control.waypoints_ne_m[0]"),
        ({"link": "udp"}, "link"),
    ],
)
def test_bad_values_name_the_key(doc, key):
    with pytest.raises(ConfigError) as e:
        config_from_dict(doc, "test.yaml")
    assert f"'{key}'" in str(e.value) and "test.yaml" in str(e.value)


def test_invalid_yaml_and_missing_file(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("mapper: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(p)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.yaml")


def test_partial_file_keeps_defaults_and_converts_types():
    cfg = config_from_dict({"mapper": {"sigma_rho": 1}, "control": {"waypoints_ne_m": [[0, 0], [10, 5]]}})
    assert cfg.mapper.sigma_rho == 1.0 and isinstance(cfg.mapper.sigma_rho, float)
    assert cfg.control.waypoints_ne_m == ((0.0, 0.0), (10.0, 5.0))
    assert cfg.mapper.max_features == CompanionConfig().mapper.max_features


def test_replace_nested():
    cfg = replace(CompanionConfig(), **{"mapper.max_features": 300, "avoidance.clearance_m": 5.0})
    assert cfg.mapper.max_features == 300 and cfg.avoidance.clearance_m == 5.0
    assert yaml.safe_load(defaults_yaml())["mapper"]["max_features"] == 50
