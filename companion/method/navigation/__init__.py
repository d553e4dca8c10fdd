"""Navigation from what the autopilot sends: the state at a frame's capture time.

* :mod:`~companion.method.navigation.assembler` - MAVLink messages -> NavState with its covariance;
* :mod:`~companion.method.navigation.timesync` - autopilot time -> companion time;
* :mod:`~companion.method.navigation.buffer` - the time-indexed history, interpolated at frame times.
"""
