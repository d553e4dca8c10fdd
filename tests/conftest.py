"""How the suite is shared between pytest-xdist workers (`pytest -n auto --dist loadgroup`).

Each test module is one unit of work, so a module's fixtures (a demo flight, a mapped world) are
built once. The demo's flights run the service in wall-paced time and must not lose frames to a
busy machine (tests/test_demo.py asserts it), and the scenario suite's flights start processes of
their own: those two modules share one worker and never run beside each other. Without `-n`
(one process) the groups change nothing.
"""

from __future__ import annotations

import pytest

# Modules whose tests load the machine with processes of their own; they run one after the other.
FLIGHT_MODULES = frozenset({"test_demo", "test_quality"})


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items):
    for item in items:
        module = item.path.stem
        item.add_marker(pytest.mark.xdist_group("flights" if module in FLIGHT_MODULES else module))
