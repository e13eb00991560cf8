"""Which config keys a stage reads, derived from its source.

The workflow gives each stage a config file holding only the keys it depends on
(``workflow/rules/common.smk``: ``stage_config``), so that a config change reruns exactly the
stages that read it. The key lists are not kept by hand: :func:`stage_keys` parses the stage's
module and the settings builders it calls (``waveforest.settings``) and collects every read of
the loaded config ``cfg``:

- ``cfg["a"]["b"]`` (and ``cfg.get("a")``) reads ``a/b``: paths are cut at depth 2;
- ``x = cfg["a"]`` makes ``x`` an alias: ``x["b"]`` reads ``a/b``;
- ``cfg`` handed to a settings builder reads what the builder reads; handed to a function of the
  same module, what that function reads (every function's ``cfg`` parameter is walked);
- ``cfg`` handed anywhere else reads the whole config (``*``).

Only the standard library is imported, so Snakemake can call it while planning.
"""

from __future__ import annotations

import ast
import functools
import importlib.util
from pathlib import Path

CFG = "cfg"
"""The name a stage gives the loaded config (``cliutil.stage_options`` passes it as ``cfg``)."""

SETTINGS_MODULE = "waveforest.settings"
"""The one module that builds typed settings from the validated config."""

DEPTH = 2
"""Key paths are cut at this depth ("section/key")."""

WHOLE = "*"
"""The path of a read of the whole config."""


def _source(module: str) -> ast.Module:
    spec = importlib.util.find_spec(module)
    if spec is None or spec.origin is None:
        raise ValueError(f"{module}: no such module")
    return ast.parse(Path(spec.origin).read_text(encoding="utf-8"))


def _key(node: ast.AST) -> str | None:
    return node.value if isinstance(node, ast.Constant) and isinstance(node.value, str) else None


class _Reads(ast.NodeVisitor):
    """The config paths one module reads through ``cfg`` and its aliases."""

    def __init__(self, builders: dict[str, frozenset], local: set[str]):
        self.builders = builders  # callable name as written -> the paths it reads
        self.local = local  # functions defined in the module (their cfg parameter is walked)
        self.paths: set[str] = set()
        self.aliases: dict[str, tuple[str, ...]] = {}

    def _chain(self, node: ast.AST) -> tuple[str, ...] | None:
        """The key path of ``node`` if it reads the config, else None."""
        keys: list[str] = []
        while True:
            if isinstance(node, ast.Subscript) and _key(node.slice) is not None:
                keys.append(_key(node.slice))
                node = node.value
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get"
                  and node.args and _key(node.args[0]) is not None):
                keys.append(_key(node.args[0]))
                node = node.func.value
            else:
                break
        if isinstance(node, ast.Name):
            if node.id == CFG:
                return tuple(reversed(keys))
            if node.id in self.aliases:
                return self.aliases[node.id] + tuple(reversed(keys))
        return None

    def _read(self, path: tuple[str, ...]) -> None:
        self.paths.add("/".join(path[:DEPTH]) if path else WHOLE)

    def _callee(self, func: ast.AST) -> str | None:
        if isinstance(func, ast.Name):
            return func.id
        if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name):
            return f"{func.value.id}.{func.attr}"
        return None

    def visit_Assign(self, node: ast.Assign) -> None:
        pairs = [(node.targets[0], node.value)] if len(node.targets) == 1 else []
        if pairs and isinstance(node.targets[0], ast.Tuple) and isinstance(node.value, ast.Tuple):
            pairs = list(zip(node.targets[0].elts, node.value.elts))
        for target, value in pairs:
            path = self._chain(value)
            if isinstance(target, ast.Name) and path is not None and path:
                self.aliases[target.id] = path
                if len(path) >= DEPTH:
                    self._read(path)
                continue
            self.visit(value)
        if not pairs:
            self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        callee = self._callee(node.func)
        path = self._chain(node)
        if path is not None:  # cfg.get("a")
            self._read(path)
            return
        for arg in list(node.args) + [k.value for k in node.keywords]:
            chain = self._chain(arg)
            if chain == () and callee in self.builders:
                self.paths |= self.builders[callee]
            elif chain == () and callee in self.local:
                pass  # the function's own cfg parameter is walked where it is defined
            elif chain is not None:
                self._read(chain)
            else:
                self.visit(arg)
        self.visit(node.func)

    def visit_Subscript(self, node: ast.Subscript) -> None:
        path = self._chain(node)
        if path is not None:
            self._read(path)
        else:
            self.generic_visit(node)

    def visit_Attribute(self, node: ast.Attribute) -> None:
        path = self._chain(node.value) if isinstance(node.value, (ast.Subscript, ast.Name)) else None
        if path is not None and node.attr in ("items", "keys", "values"):
            self._read(path)
        else:
            self.generic_visit(node)

    def visit_Name(self, node: ast.Name) -> None:
        if node.id == CFG:
            self._read(())
        elif node.id in self.aliases:
            self._read(self.aliases[node.id])


def _module_reads(tree: ast.Module, builders: dict[str, frozenset]) -> set[str]:
    local = {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    reads = _Reads(builders, local)
    for node in tree.body:
        reads.visit(node)
    return reads.paths


@functools.cache
def builder_keys() -> dict[str, frozenset]:
    """Config paths read by each public function of :mod:`waveforest.settings`, by name.

    Builders may call each other: the paths are iterated to a fixed point."""
    tree = _source(SETTINGS_MODULE)
    functions = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef) and not n.name.startswith("_")}
    out: dict[str, frozenset] = {name: frozenset() for name in functions}
    changed = True
    while changed:
        changed = False
        for name, fn in functions.items():
            reads = _Reads({k: v for k, v in out.items() if k != name}, set())
            reads.visit(fn)
            if frozenset(reads.paths) != out[name]:
                out[name], changed = frozenset(reads.paths), True
    return out


def _builder_names(tree: ast.Module) -> dict[str, frozenset]:
    """The settings builders as a module may call them (``settings.x`` or an imported ``x``)."""
    keys = builder_keys()
    names: dict[str, frozenset] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "waveforest":
            for alias in node.names:
                if alias.name == "settings":
                    names.update({f"{alias.asname or 'settings'}.{k}": v for k, v in keys.items()})
        elif isinstance(node, ast.ImportFrom) and node.module == SETTINGS_MODULE:
            names.update({alias.asname or alias.name: keys[alias.name] for alias in node.names if alias.name in keys})
    return names


def normalise(paths) -> tuple[str, ...]:
    """Sorted paths without those covered by a shorter one (``a`` covers ``a/b``)."""
    paths = set(paths)
    return tuple(sorted(p for p in paths if p.split("/")[0] not in paths or "/" not in p))


def stage_keys(module: str) -> tuple[str, ...]:
    """The config paths ("section" or "section/key", or ``*`` for all) that a stage module reads."""
    tree = _source(module)
    return normalise(_module_reads(tree, _builder_names(tree)))
