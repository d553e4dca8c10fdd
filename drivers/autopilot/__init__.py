"""The autopilot link (MAVLink 2 over UDP, TCP or a serial port), one file per responsibility.

* :mod:`~drivers.autopilot.link` - :class:`AutopilotLink`: the connection's life, heartbeat, signing, sending;
* :mod:`~drivers.autopilot.connection` - connection strings -> :class:`Endpoint`;
* :mod:`~drivers.autopilot.transport` - UDP, TCP and serial byte pipes on asyncio;
* :mod:`~drivers.autopilot.framing` - MAVLink 2 framing and signature checks of received bytes;
* :mod:`~drivers.autopilot.receive` - frames -> handlers; navigation messages -> NavState -> the buffer;
* :mod:`~drivers.autopilot.streams` - the message streams asked of the autopilot;
* :mod:`~drivers.autopilot.timing` - TIMESYNC and the autopilot's reboots;
* :mod:`~drivers.autopilot.commanding` - commands, setpoints, STATUSTEXT;
* :mod:`~drivers.autopilot.status` - the link's status for the operator;
* :mod:`~drivers.autopilot.protocol`, :mod:`~drivers.autopilot.meters` - MAVLink values; rates and rate-limited logs.

docs/mavlink.md describes the behaviour.
"""
