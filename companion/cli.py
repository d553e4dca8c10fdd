"""The ``companion`` command line.

Each subcommand lives in its own module, which provides ``configure_parser(parser)`` and
``main(args) -> int``; this file only routes to them, importing a module when its command runs.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("companion.desk.demo.command", "closed-loop demo: simulated vehicle + daemon + ground station, writes a report"),
    "run": ("companion.service.daemon", "run the service (the systemd unit runs this)"),
    "sim": ("drivers.sim.vehicle", "simulated multirotor that speaks MAVLink (ArduPilot or PX4 flavour)"),
    "quality": ("companion.desk.quality.suite", "the scenario suite: what a pilot sees, over scenarios x seeds x mappers"),
    "replay": ("companion.desk.replay", "run the mapper over a recording as fast as possible"),
    "ground": ("drivers.ground_station", "ground-station subscriber: reassembles the map from Zenoh"),
    "router": ("drivers.zenoh_router", "Zenoh router for a fleet: vehicles and ground stations connect to it"),
    "config": ("companion.config_cli", "print the default configuration or check a file"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module_name)
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name and module_name.startswith(exc.name):
                p.set_defaults(_missing=True)
                continue
            raise
        module.configure_parser(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    # One BLAS / OpenMP thread, set before the subcommands' imports load NumPy (too late after):
    # the service's matrix products are small, and idle OpenBLAS threads spinning on a 2-4 core
    # board steal the core from the control loop (docs/performance.md). An explicit setting wins.
    for name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
        os.environ.setdefault(name, "1")
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.command:
        parser.print_help()
        return 2
    if getattr(args, "_missing", False):
        print(f"companion {args.command}: not available in this build yet", file=sys.stderr)
        return 2
    module = importlib.import_module(args._module)
    try:
        return int(module.main(args) or 0)
    except RuntimeError as exc:
        from companion.desk.plots import DeskExtraMissing  # only a desk tool's figures raise it

        if not isinstance(exc, DeskExtraMissing):
            raise
        print(f"companion {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
