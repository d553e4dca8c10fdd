"""The service on the vehicle: the daemon (``companion run``) and what only it uses.

The daemon wires the method to the edges in one asyncio TaskGroup; the mapper's child process,
real-time scheduling of the control loop and the systemd notifications serve it alone.
Imports the method and the drivers, never a desk tool (docs/architecture.md).
"""
