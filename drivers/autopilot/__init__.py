"""The autopilot link: MAVLink 2 over UDP, TCP or a serial port (docs/mavlink.md)."""
