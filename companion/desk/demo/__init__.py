"""``companion demo``: the closed loop on this machine, with a report (docs/demo.md)."""
