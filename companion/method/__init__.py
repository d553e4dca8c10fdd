"""The method: monocular terrain mapping and terrain avoidance as pure computation.

Navigation assembly from autopilot messages, the mapper, the terrain evidence grid, the
avoidance law, guidance and the control decision. Nothing here opens a socket, starts a task
or reads a clock; the one file access is the terrain map's snapshot format (terrain/persistence.py).
Imports nothing of the project outside this package but ``companion.config`` (docs/architecture.md).
"""
