"""The layout is the architecture: stages in one folder, no import cycle, no fixtures in src/."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import click
import pytest

from waveforest.cli import COMMANDS, help_line, short_help

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
    flat = " ".join(out.split())
    for name, target in COMMANDS.items():
        module, attr = target.split(":")
        command = getattr(importlib.import_module(module), attr)
        line = short_help(target)
        assert line == help_line(command) and not line.endswith("..."), name
        assert f" {name} {line}" in flat, name


# -- the house: layers, imports, config keys ------------------------------------------------------

LAYERS = (
    ("waveforest", "waveforest.errors", "waveforest.constants", "waveforest.species", "waveforest.rng",
     "waveforest.atomic", "waveforest.plotting", "waveforest.effects", "waveforest.config",
     "waveforest.config_keys", "waveforest.workers", "waveforest.scene"),
    ("waveforest.io",),
    ("waveforest.vegetation", "waveforest.mcrt", "waveforest.sensor"),
    ("waveforest.model",),
    ("waveforest.survey",),
    ("waveforest.campaign",),
    ("waveforest.stats",),
    ("waveforest.analysis",),
    ("waveforest.diagnose",),
    ("waveforest.report",),
    ("waveforest.settings",),
    ("waveforest.cliutil",),
    ("waveforest.stages",),
    ("waveforest.cli",),
)
"""Layers from the base up (docs/design.md): a module imports its own package or lower layers only."""

FUNCTION_LEVEL_IMPORTS = {
    "tqdm": "progress bars, loaded only when one is shown",
    "matplotlib": "figures, loaded only when one is drawn",
    "scipy": "a few special functions and optimisers, loaded where used",
    "sklearn": "the LDA and its folds (~80 MB, ~1 s), loaded only by the commands that classify",
}
"""Modules that may be imported inside a function (heavy and needed only on some paths)."""

FUNCTION_LEVEL_EXCEPTIONS = {
    ("waveforest.stages.trace", "waveforest.vegetation"): "a PLY trace builds no plant (scipy, Numba kernels)",
    ("waveforest.settings", "*"): "each builder loads its own stage's settings class, so a command starts "
                                  "with the modules it runs, not every stage's (`trace --help` 0.86 -> 0.66 s)",
}
"""(importing module, imported module or ``*``) pairs also allowed inside a function, each with its reason."""


def _package(module: str) -> str:
    """The unit a module belongs to in LAYERS (a subpackage, or a base module)."""
    for layer in LAYERS:
        for unit in sorted(layer, key=len, reverse=True):
            if unit != "waveforest" and (module == unit or module.startswith(unit + ".")):
                return unit
    return "waveforest"


def _rank(module: str) -> int:
    unit = _package(module)
    return next(i for i, layer in enumerate(LAYERS) if unit in layer)


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _module_level_imports(name, path, modules) for name, path in modules.items()}


def test_every_module_has_a_layer():
    named = {u for layer in LAYERS for u in layer}
    for name in _modules():
        assert _package(name) in named, name
    base = {n for n in _modules() if _package(n) == "waveforest"}
    assert base <= set(LAYERS[0]), f"base modules not in LAYERS[0]: {base - set(LAYERS[0])}"


def test_imports_point_down_the_layers():
    """Upwards never; sideways only among the base modules (no cycle: test above)."""
    bad = [f"{a} -> {b}" for a, targets in _graph().items() for b in targets
           if _package(a) != _package(b) and (_rank(b) > _rank(a) or _rank(b) == _rank(a) > 0)]
    assert not bad, bad


def test_no_package_pair_imports_each_other():
    edges = {(_package(a), _package(b)) for a, targets in _graph().items() for b in targets
             if _package(a) != _package(b)}
    assert not [e for e in edges if e[::-1] in edges]


def test_no_stage_imports_another_and_nothing_below_imports_stages():
    bad = [f"{a} -> {b}" for a, targets in _graph().items() for b in targets
           if b.startswith("waveforest.stages.") and not a == "waveforest.cli"]
    assert not bad, bad


def _imports_in_functions(tree: ast.Module) -> list[tuple[str, int]]:
    found = []
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in ast.walk(fn):
                if isinstance(node, ast.Import):
                    found += [(a.name, node.lineno) for a in node.names]
                elif isinstance(node, ast.ImportFrom) and not node.level:
                    found.append((node.module, node.lineno))
    return found


def test_function_level_imports_only_for_heavy_optional_modules():
    bad = []
    for name, path in _modules().items():
        for target, line in _imports_in_functions(ast.parse(path.read_text())):
            if (target.split(".")[0] in FUNCTION_LEVEL_IMPORTS or (name, target) in FUNCTION_LEVEL_EXCEPTIONS
                    or (name, "*") in FUNCTION_LEVEL_EXCEPTIONS):
                continue
            bad.append(f"{path.relative_to(SRC)}:{line}: {target}")
    assert not bad, bad


def test_no_private_name_crosses_a_module():
    modules = _modules()
    bad = []
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        imported_modules = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("waveforest"):
                for a in node.names:
                    if a.name.startswith("_") and not a.name.startswith("__"):
                        bad.append(f"{name}: from {node.module} import {a.name}")
                    if f"{node.module}.{a.name}" in modules:
                        imported_modules[a.asname or a.name] = f"{node.module}.{a.name}"
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("waveforest") and a.asname:
                        imported_modules[a.asname] = a.name
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in imported_modules and node.attr.startswith("_")
                    and not node.attr.startswith("__")):
                bad.append(f"{name}: {imported_modules[node.value.id]}.{node.attr}")
    assert not bad, bad


def test_nothing_below_the_stages_reads_a_raw_config():
    """Only stages, the settings builders and the config module itself index a loaded config."""
    allowed = ("waveforest.stages", "waveforest.settings", "waveforest.config", "waveforest.cliutil",
               "waveforest.config_keys")
    bad = []
    for name, path in _modules().items():
        if name.startswith(allowed):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name)
                    and node.value.id in ("cfg", "config")):
                bad.append(f"{path.relative_to(SRC)}:{node.lineno}")
            elif isinstance(node, ast.arg) and node.arg == "cfg":
                bad.append(f"{path.relative_to(SRC)}:{node.lineno}: a cfg parameter")
    assert not bad, bad


def _rule_stages() -> dict[str, str]:
    """rule config name -> stage module, from the stage_config calls of workflow/rules/*.smk."""
    out = {}
    for smk in (SRC.parent / "workflow" / "rules").glob("*.smk"):
        for node in ast.walk(ast.parse(_python_of(smk.read_text()))):
            if (isinstance(node, ast.Call) and getattr(node.func, "id", "") == "stage_config"
                    and all(isinstance(a, ast.Constant) for a in node.args)):
                args = [a.value for a in node.args]
                out[args[0]] = args[1] if len(args) > 1 else args[0]
    return out


def _python_of(smk: str) -> str:
    """The stage_config(...) calls of a Snakemake file as Python expressions, one per line."""
    import re

    return "\n".join(m.group(0) for m in re.finditer(r"stage_config\([^()]*\)", smk))


def test_each_rule_depends_on_the_config_keys_its_stage_reads():
    """The keys are derived (config_keys.stage_keys); each must exist in the validated config,
    and only the report (which prints the whole config) reads all of it."""
    from waveforest import config as config_module
    from waveforest.config_keys import stage_keys

    rules = _rule_stages()
    assert {"simulate", "select", "diagnose", "features_real", "report"} <= set(rules), rules
    cfg = config_module.load(None)
    for rule, module in rules.items():
        keys = stage_keys(f"waveforest.stages.{module}")
        assert keys, rule
        if module == "report":
            assert keys == ("*",), keys
            continue
        assert "*" not in keys, f"stage {module} hands the whole config on: {keys}"
        for key in keys:
            node = cfg
            for part in key.split("/"):
                assert isinstance(node, dict) and part in node, f"{rule}: {key} is no config key"
                node = node[part]


class _Recording(dict):
    """A config mapping that records the key paths read from it."""

    def __init__(self, data, reads, path=()):
        super().__init__(data)
        self._reads, self._path = reads, path

    def __getitem__(self, key):
        value = super().__getitem__(key)
        path = self._path + (key,)
        self._reads.add("/".join(path[:2]))
        return _Recording(value, self._reads, path) if isinstance(value, dict) else value

    def get(self, key, default=None):
        return self[key] if key in self else default


def test_settings_builders_read_what_the_static_analysis_says():
    """Each builder of waveforest.settings that takes the config alone is run on a recording
    config: the keys it reads at run time are the ones config_keys derives from its source."""
    import inspect

    from waveforest import config as config_module
    from waveforest import settings
    from waveforest.config_keys import builder_keys, normalise

    static = builder_keys()
    checked = 0
    for name, keys in static.items():
        fn = getattr(settings, name)
        params = list(inspect.signature(fn).parameters.values())
        if not params or params[0].name != "cfg" or any(p.default is inspect.Parameter.empty for p in params[1:]):
            continue
        reads: set[str] = set()
        fn(_Recording(config_module.load(None), reads))
        derived = normalise(keys)
        leaves = {r for r in reads if not any(o.startswith(r + "/") for o in reads)}
        covered = {r for r in leaves if any(r == k or r.startswith(k + "/") for k in derived)}
        assert covered == leaves, (name, sorted(leaves - covered))
        assert all(any(r == k or r.startswith(k + "/") for r in leaves) for k in derived), (name, derived)
        checked += 1
    assert checked >= 3, checked
