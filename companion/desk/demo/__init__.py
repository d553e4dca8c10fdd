"""``companion demo``: the closed loop on this machine, with a report.

For each parameterisation asked for (inverse depth, then the Cartesian baseline), one run:

```
companion sim  (subprocess) --TCP MAVLink--> companion run (subprocess, generated YAML)
      |  --UDP MAVLink--> this process: the "pilot" (GUIDED, arm, take off; logs SIM_STATE truth)
companion run --Zenoh--> this process: the ground station (tiles, status, avoidance)
```

The demo plays the operator: it arms the simulated vehicle and takes off to the circuit
altitude; above ``control.min_alt_m`` the service flies the circuit, maps the terrain with the
synthetic camera and keeps its clearance. The truth trajectory (SIM_STATE) splits into laps;
at each lap's end the ground station's map is kept. After the laps asked for, the service and
the simulator get SIGTERM (the service must save its map and exit within a few seconds).

Then :mod:`companion.desk.report` turns trajectories and maps into ``metrics.json`` and the PNGs
(docs/demo.md describes both). Nothing is tuned per run: the figures are what the loop did.

The modules:

* :mod:`~companion.desk.demo.command` - ``companion demo``: options, the runs, the report folder;
* :mod:`~companion.desk.demo.flight` - one closed-loop run: the processes, the loop, the laps;
* :mod:`~companion.desk.demo.pilot` - the operator: GUIDED, arm, take off; the truth trajectory;
* :mod:`~companion.desk.demo.progress` - a run's progress on stderr;
* :mod:`~companion.desk.demo.results` - ``metrics.json`` and the saved runs (``--replot``);
* :mod:`~companion.desk.demo.figures` - the PNGs.
"""
