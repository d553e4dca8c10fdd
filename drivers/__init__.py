"""The edges of the service: autopilot link, cameras, Zenoh bus, and simulated stand-ins for hardware."""
