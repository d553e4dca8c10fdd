"""Which layout a folder holds (:func:`detect_kind`), and opening a recording of any of them
(:func:`open_recording`): the service's own, a TUM folder, EuRoC MAV or a COLMAP text model."""

from __future__ import annotations

from pathlib import Path

from companion.config import CompanionConfig, ConfigError, config_from_dict
from companion.desk.recordings.colmap import colmap_model_dir, open_colmap
from companion.desk.recordings.euroc import EUROC_CAM_CSV, euroc_root, open_euroc
from companion.desk.recordings.recording import IDENTITY_MOUNT, Overrides, Recording, RecordingError, first_existing
from companion.desk.recordings.telemetry import open_companion
from companion.desk.recordings.tum import TUM_CAMERA, TUM_POSES, open_tum
from companion.method.geometry import CameraMount


def detect_kind(path: Path) -> str:
    """``companion``, ``euroc``, ``colmap`` or ``tum`` from the files present; RecordingError if none
    fits. A COLMAP model is told from a TUM folder (both have an ``images.txt``) by its ``cameras.txt``."""
    path = Path(path)
    if not path.is_dir():
        raise RecordingError(f"{path}: not a folder")
    if (path / "frames.csv").is_file() and (path / "meta.yaml").is_file():
        return "companion"
    if (euroc_root(path) / EUROC_CAM_CSV).is_file():
        return "euroc"
    if colmap_model_dir(path) is not None:
        return "colmap"
    if first_existing(path, TUM_POSES) is not None or (path / TUM_CAMERA).is_file():
        return "tum"
    raise RecordingError(
        f"{path}: not a recording: expected meta.yaml + frames.csv (companion --record), "
        f"mav0/cam0/data.csv (EuRoC), poses.txt + camera.yaml + meta.yaml (TUM folder) or cameras.txt + "
        f"images.txt (+ sparse/0; COLMAP text model)"
    )


def open_recording(path: str | Path, cfg: CompanionConfig | None = None, *, kind: str = "auto",
                   overrides: Overrides = Overrides(), mount: CameraMount = IDENTITY_MOUNT) -> Recording:
    """Open a recording of any supported layout. ``cfg`` supplies the nav settings (interpolation
    limits, telemetry assembly); ``mount`` is the body frame pose-given layouts report (identity:
    the body is the camera)."""
    path = Path(path).expanduser()
    cfg = cfg or CompanionConfig()
    kind = detect_kind(path) if kind == "auto" else kind
    if kind == "companion":
        return open_companion(path, cfg, overrides)
    if kind == "tum":
        rec = open_tum(path, cfg.nav, overrides, mount)
    elif kind == "euroc":
        rec = open_euroc(path, cfg.nav, overrides, mount)
    elif kind == "colmap":
        rec = open_colmap(path, cfg.nav, overrides, mount)
    else:
        raise RecordingError(f"unknown recording kind {kind!r} (auto, companion, tum, euroc, colmap)")
    rec.kind = kind
    return rec


def recording_config(path: Path) -> CompanionConfig | None:
    """The configuration stored in a companion recording's ``meta.yaml`` (None for other layouts,
    or when it does not validate with this version: the caller falls back and says so)."""
    try:
        if detect_kind(path) != "companion":
            return None
    except RecordingError:
        return None
    from drivers.cameras.recorder import read_recording_meta

    try:
        return config_from_dict(read_recording_meta(path).get("config") or {}, str(path / "meta.yaml"))
    except (ConfigError, ValueError):
        return None
