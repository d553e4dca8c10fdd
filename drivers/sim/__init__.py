"""Simulated stand-ins for hardware: the world, its renderer, and a vehicle that speaks MAVLink."""
