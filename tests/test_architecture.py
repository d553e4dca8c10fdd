"""The layers of docs/architecture.md, as the code holds them: every module's project imports (at the
top, inside functions, relative or absolute) point one way, the folder list is the layers, and the
method stays free of I/O libraries.

    desk tools (companion/desk)  ->  service (companion/service)  ->  edges (drivers)  ->  method (companion/method)

companion/config.py imports nothing of the project; every layer may import it. The command line
(companion/cli.py) routes to any layer by name, importing a command's module when it runs.
"""

from __future__ import annotations

import ast
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("companion", "drivers")

# layer -> the layers its modules may import (its own included)
ALLOWED: dict[str, frozenset[str]] = {
    "config": frozenset({"config"}),
    "config_cli": frozenset({"config", "config_cli"}),
    "method": frozenset({"config", "method"}),
    "drivers": frozenset({"config", "method", "drivers"}),
    "service": frozenset({"config", "method", "drivers", "service"}),
    "desk": frozenset({"config", "method", "drivers", "service", "desk"}),
    "cli": frozenset({"config", "config_cli", "method", "drivers", "service", "desk", "cli"}),
    "package": frozenset({"package"}),
}
LAYER_NAMES = {
    "config": "the configuration (companion/config.py)",
    "config_cli": "'companion config' (companion/config_cli.py)",
    "method": "the method (companion/method)",
    "drivers": "the edges (drivers)",
    "service": "the service (companion/service)",
    "desk": "the desk tools (companion/desk)",
    "cli": "the command line (companion/cli.py)",
    "package": "the package itself (companion/__init__.py)",
}
# What companion/ holds at its top: the entry point, the configuration, and one folder per layer.
COMPANION_TOP = {"__init__.py", "cli.py", "config.py", "config_cli.py", "py.typed", "method", "service", "desk"}
# Libraries that do I/O or run things concurrently: never in the method (a file of the map's own
# snapshot format is its one file access, companion/method/terrain/persistence.py).
NOT_IN_METHOD = {"asyncio", "socket", "subprocess", "multiprocessing", "selectors", "signal", "pymavlink", "mavsdk",
                 "zenoh", "matplotlib", "http", "urllib"}


def layer_of(module: str) -> str | None:
    """The layer of a project module name, None for a name outside companion and drivers."""
    parts = module.split(".")
    if parts[0] == "drivers":
        return "drivers"
    if parts[0] != "companion":
        return None
    if len(parts) == 1:
        return "package"
    top = parts[1]
    if top in ("method", "service", "desk"):
        return top
    return {"config": "config", "config_cli": "config_cli", "cli": "cli"}.get(top, f"unknown top-level module companion.{top}")


@dataclass(frozen=True)
class Import:
    path: Path  # the importing file
    line: int
    module: str  # the project module imported (the deepest name that is a module or package)


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def is_module(name: str) -> bool:
    base = ROOT.joinpath(*name.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def imports_of(path: Path) -> list[Import]:
    """Every import of a project module in ``path``: top level, inside functions and classes, relative too."""
    me = module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            # `from companion.desk import plots` imports the module companion.desk.plots
            names = [f"{source}.{a.name}" if is_module(f"{source}.{a.name}") else source for a in node.names]
        else:
            continue
        for name in names:
            if name.split(".")[0] in PACKAGES:
                found.append(Import(path, node.lineno, name))
    return found


def project_files() -> list[Path]:
    return sorted(p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py") if "__pycache__" not in p.parts)


def test_the_scan_sees_every_kind_of_import():
    """The checks below rest on this: imports at the top, in functions, from a package and relative are all found."""
    daemon = {i.module for i in imports_of(ROOT / "companion/service/daemon.py")}
    assert "companion.service.realtime" in daemon  # `from companion.service import realtime`
    assert "drivers.autopilot.link" in daemon  # inside Daemon.__init__
    assert "companion.config" in daemon
    assert len(project_files()) > 100


@pytest.mark.parametrize("path", project_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_point_one_way(path):
    """tools -> service -> edges -> method; the configuration under all of them; nothing the other way."""
    own = layer_of(module_name(path))
    assert own in ALLOWED, f"{path.relative_to(ROOT)} is in no layer ({own}); docs/architecture.md lists them"
    wrong = [f"{path.relative_to(ROOT)}:{i.line} imports {i.module} ({LAYER_NAMES.get(layer_of(i.module), layer_of(i.module))})"
             for i in imports_of(path) if layer_of(i.module) not in ALLOWED[own]]
    allowed = ", ".join(LAYER_NAMES[k] for k in sorted(ALLOWED[own]))
    assert not wrong, f"{LAYER_NAMES[own]} may import only {allowed}:\n" + "\n".join(wrong)


def test_the_method_uses_no_io_library():
    """The method computes; sockets, processes, event loops, links, buses and figures belong to the other layers."""
    wrong = []
    for path in (ROOT / "companion" / "method").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            wrong += [f"{path.relative_to(ROOT)}:{node.lineno} imports {n}" for n in names if n.split(".")[0] in NOT_IN_METHOD]
    assert not wrong, "the method must stay pure:\n" + "\n".join(wrong)


def test_only_the_desk_tools_draw_with_matplotlib():
    """The vehicle installs the package without the desk extra: nothing outside companion/desk imports matplotlib."""
    wrong = []
    for path in project_files():
        if layer_of(module_name(path)) == "desk":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            wrong += [f"{path.relative_to(ROOT)}:{node.lineno}" for n in names if n.split(".")[0] == "matplotlib"]
    assert not wrong, "matplotlib outside the desk tools:\n" + "\n".join(wrong)


def test_the_folder_list_is_the_layers():
    """companion/ holds the entry point, the configuration and one folder per layer, nothing beside them."""
    top = {p.name for p in (ROOT / "companion").iterdir() if p.name != "__pycache__"}
    assert top == COMPANION_TOP, f"unexpected in companion/: {sorted(top - COMPANION_TOP)}; missing: {sorted(COMPANION_TOP - top)}"


def test_every_command_routes_to_a_module_of_its_layer():
    """`companion COMMAND` imports its module by name when it runs: the names exist and sit in the right layer."""
    from companion.cli import COMMANDS

    expected = {"run": "service", "demo": "desk", "replay": "desk", "quality": "desk", "sim": "drivers",
                "ground": "drivers", "router": "drivers", "config": "config_cli"}
    assert set(COMMANDS) == set(expected)
    for command, (module, _) in COMMANDS.items():
        assert importlib.util.find_spec(module) is not None, f"companion {command}: no module {module}"
        assert layer_of(module) == expected[command], f"companion {command} routes to {module}, not to {expected[command]}"
