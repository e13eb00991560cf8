"""The layout is the architecture: stages in one folder, no import cycle, no fixtures in src/."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import click
import pytest

from waveforest.cli import COMMANDS, short_help

SRC = Path(__file__).resolve().parents[1] / "src"
PACKAGE = SRC / "waveforest"


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(SRC).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _module_level_imports(name: str, path: Path, modules: dict) -> set[str]:
    """waveforest modules that ``name`` imports at module level (the statement's own target, and
    the submodule when ``from package import submodule``)."""
    found: set[str] = set()

    def visit(body):
        for node in body:
            if isinstance(node, (ast.If, ast.Try)):
                visit(node.body)
                visit(node.orelse)
                for handler in getattr(node, "handlers", []):
                    visit(handler.body)
            elif isinstance(node, ast.Import):
                found.update(a.name for a in node.names if a.name.startswith("waveforest"))
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                    package = package[: len(package) - node.level + 1]
                    base = ".".join(package + ([node.module] if node.module else []))
                if base.startswith("waveforest"):
                    found.add(base)
                    found.update(f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in modules)

    visit(ast.parse(path.read_text()).body)
    return {m for m in found if m in modules and m != name}


def test_no_import_cycle_among_modules():
    modules = _modules()
    graph = {name: _module_level_imports(name, path, modules) for name, path in modules.items()}
    state: dict[str, int] = {}  # 1 = on the stack, 2 = done

    def walk(node, stack):
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = stack[stack.index(nxt):] + [nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                walk(nxt, stack + [nxt])
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            walk(name, [name])


def test_lower_layers_do_not_import_stages_diagnose_or_the_cli():
    modules = _modules()
    upper = ("waveforest.stages", "waveforest.cli", "waveforest.diagnose")
    lower = ("waveforest.io", "waveforest.vegetation", "waveforest.mcrt", "waveforest.sensor", "waveforest.model",
             "waveforest.campaign", "waveforest.stats", "waveforest.report", "waveforest.config", "waveforest.rng",
             "waveforest.scene", "waveforest.plotting", "waveforest.species")
    bad = [f"{name} -> {target}"
           for name, path in modules.items() if name.startswith(lower)
           for target in _module_level_imports(name, path, modules) if target.startswith(upper)]
    assert not bad, bad
    for a, b in (("waveforest.mcrt", "waveforest.vegetation"), ("waveforest.vegetation", "waveforest.mcrt")):
        crossing = [name for name, path in modules.items() if name.startswith(a)
                    and any(t.startswith(b) for t in _module_level_imports(name, path, modules))]
        assert not crossing, f"{a} must not import {b}: {crossing}"


def test_no_test_fixtures_ship_in_src():
    assert not list(PACKAGE.rglob("synthetic.py")) and not list(PACKAGE.rglob("bench.py"))
    for path in PACKAGE.rglob("*.py"):
        tree = ast.parse(path.read_text())
        names = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        names |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        assert not any(m.split(".")[0] in ("fixtures", "tests", "pytest") for m in names), path


def test_every_subcommand_is_a_stage_module():
    stages = {p.stem for p in (PACKAGE / "stages").glob("*.py")} - {"__init__"}
    seen = set()
    for name, target in COMMANDS.items():
        module, attr = target.split(":")
        assert module.startswith("waveforest.stages."), target
        command = getattr(importlib.import_module(module), attr)
        assert isinstance(command, click.Command) and command.name == name
        seen.add(module.rsplit(".", 1)[1])
    assert seen == stages, f"stage modules without a subcommand: {stages - seen}"


def test_group_help_lines_are_the_commands_own_without_importing_them():
    """``waveforest --help`` reads each command's line from its source; it must be the line
    click makes from the imported command, and the stage modules must stay unimported."""
    code = ("import sys; from click.testing import CliRunner; from waveforest.cli import cli; "
            "r = CliRunner().invoke(cli, ['--help']); print(r.output); "
            "print(sorted(m for m in sys.modules if m.startswith('waveforest.stages.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.rstrip().endswith("[]"), out
    for name, target in COMMANDS.items():
        module, attr = target.split(":")
        command = getattr(importlib.import_module(module), attr)
        assert short_help(target) == command.get_short_help_str(limit=70), name
        assert f"  {name} " in out, name
