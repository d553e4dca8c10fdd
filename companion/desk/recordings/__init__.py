"""Recordings the mapper can replay: the service's own, TUM folders and EuRoC MAV (docs/replay.md)."""
