"""Camera sources: V4L2 devices, recorded files, and the synthetic camera of the simulated world."""

from drivers.cameras.base import CameraError, CameraSource, CorruptInput, EndOfStream

__all__ = ["CameraError", "CameraSource", "CorruptInput", "EndOfStream"]
