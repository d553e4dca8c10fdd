"""Build the camera source ``camera.source`` names."""

from __future__ import annotations

from typing import Any

from companion.config import CameraConfig, ConfigError
from drivers.cameras.base import CameraSource
from drivers.clock import Clock


def build_camera(config: CameraConfig, clock: Clock, **kwargs: Any) -> CameraSource:
    """A :class:`V4L2Source` for ``v4l2``, a recorded source for ``file``.

    ``kwargs`` go to the source's constructor (e.g. ``capture_factory`` for V4L2, ``offset_s`` for
    a recording). ``synthetic`` is refused here: that camera renders the simulated world, which
    the daemon builds (``drivers.cameras.synthetic``) from the scenario and the vehicle's truth.
    Raises :class:`ConfigError` for a configuration that cannot work (missing file, bad FOURCC,
    recording of the wrong size); an absent V4L2 device is not an error here (the source keeps
    trying to open it).
    """
    if config.source == "v4l2":
        from drivers.cameras.v4l2 import V4L2Source

        return V4L2Source(config, clock, **kwargs)
    if config.source == "file":
        from drivers.cameras.recorded import open_recording

        return open_recording(config, clock, **kwargs)
    if config.source == "synthetic":
        raise ConfigError(
            "camera.source 'synthetic' is built by the daemon from the simulated world "
            "(drivers.cameras.synthetic needs the scenario and the vehicle state), not by build_camera"
        )
    if config.source == "stream":
        raise ConfigError(
            "camera.source 'stream' is built by the daemon (drivers.cameras.stream needs the autopilot link's "
            "time synchronisation to place the frames on the companion clock), not by build_camera"
        )
    raise ConfigError(f"camera.source: unknown source {config.source!r} (v4l2, file, synthetic, stream)")
