"""The interface every camera source implements.

A source yields :class:`companion.method.messages.Frame` objects stamped at capture on the companion
clock. Reading is async; blocking device or file reads run in a worker thread inside the source.
"""

from __future__ import annotations

import abc

from companion.method.messages import Frame


class CameraError(RuntimeError):
    """The device is unavailable (vanished, not opened yet); the source may recover (reconnect)."""


class EndOfStream(Exception):
    """A recorded source has no more frames."""


class CorruptInput(RuntimeError):
    """A recording is broken from here on; frames already read remain valid."""


class CameraSource(abc.ABC):
    """An async source of grayscale frames."""

    name: str = "camera"

    @abc.abstractmethod
    async def read(self) -> Frame:
        """Next frame. Raises :class:`CameraError` (transient), :class:`EndOfStream` or :class:`CorruptInput`."""

    async def close(self) -> None:  # noqa: B027 - optional for sources with nothing to release
        """Release the device or file."""

    async def __aenter__(self) -> "CameraSource":
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()
