"""The scenario suite: what a pilot sees, measured on many simulated worlds (docs/quality.md).

* :mod:`companion.quality.scenarios` - the service configuration a scenario implies, with overrides;
* :mod:`companion.quality.engine` - the service's closed loop in one process, in simulated time;
* :mod:`companion.quality.metrics` - the pilot's figures, pure functions of a flight's record;
* :mod:`companion.quality.figures` - side profiles (matplotlib);
* :mod:`companion.quality.suite` - ``companion quality``: scenarios x seeds x parameterisations.
"""
