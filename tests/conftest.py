"""How the suite is shared between pytest-xdist workers (`pytest -n auto --dist loadgroup`).

Each test module is one unit of work, so a module's fixtures (a mapped world, a flown scenario)
are built once. A module with two costly flights of its own (the demo's closed loop and its
same-path comparison) is split by the flight each test reads, so that the two fly on two workers
at once. The demo's flights run in lockstep with the service (docs/sim.md, "Lockstep"): on a busy
worker they run slower, never blind, so no module needs a worker to itself. Without `-n` (one
process) the groups change nothing.
"""

from __future__ import annotations

import pytest

# Module-scoped fixtures that each fly a whole demo: the tests that read one form a unit of their own.
FLIGHT_FIXTURES = ("closed_loop_run", "same_path_run")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items):
    for item in items:
        flights = [name for name in FLIGHT_FIXTURES if name in getattr(item, "fixturenames", ())]
        item.add_marker(pytest.mark.xdist_group(flights[0] if flights else item.path.stem))
