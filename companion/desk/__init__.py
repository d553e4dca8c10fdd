"""The desk tools: what runs on a desk, never on the vehicle.

``companion demo`` (the closed loop with a report), ``companion replay`` (the mapper over a
recording), ``companion quality`` (the scenario suite), and the metrics and figures they share.
They may use everything else: the method, the service, the drivers and the simulator
(docs/architecture.md). Their figures need matplotlib, the ``desk`` extra.
"""
