"""docs/architecture.md's import rules, read from the source: every import of our packages (module level, inside
functions, not under ``TYPE_CHECKING``), the layer table, the narrower rules, and no import circle between modules
(type-only imports included)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# the table of docs/architecture.md "Packages and what each may import"
MAY_IMPORT = {
    "schemas": set(),
    "regression": {"schemas"},
    "simulator_bridge": {"schemas"},
    "training": {"schemas", "regression", "simulator_bridge"},
    "agent": {"schemas", "regression"},
    "recordings": {"schemas", "regression", "agent"},
    "adapters": {"schemas", "simulator_bridge"},  # narrowed in _narrower
    "cvvc": {"schemas", "regression", "simulator_bridge", "training", "agent", "recordings", "adapters"},
    "benchmarks": {"schemas", "regression", "simulator_bridge", "training", "agent", "recordings", "adapters",
                   "cvvc"},
}
OURS = set(MAY_IMPORT)


def _module(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def _is_module(name: str) -> bool:
    p = ROOT.joinpath(*name.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _imports(path: Path, *, typing: bool = False) -> list[tuple[str, int]]:
    """(imported name, line) of every import of ours or of opendssdirect in ``path``; those under ``TYPE_CHECKING``
    only with ``typing`` (a type-only import still ties the two modules: a circle of them is a circle)."""
    tree = ast.parse(path.read_text())
    typing_only = set() if typing else {
        id(n) for g in ast.walk(tree) if isinstance(g, ast.If) and "TYPE_CHECKING" in ast.unparse(g.test)
        for b in g.body for n in ast.walk(b)}
    out = []
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        out += [(n, node.lineno) for n in names if n.split(".")[0] in OURS | {"opendssdirect"}]
    return out


def _all_imports(*, typing: bool = False) -> dict[str, list[tuple[str, int]]]:
    return {_module(f): _imports(f, typing=typing) for pkg in sorted(OURS) for f in sorted((ROOT / pkg).rglob("*.py"))}


def _narrower(module: str, name: str) -> str | None:
    """The rules finer than a package: who may import OpenDSS, which of simulator_bridge's rooms the others may use."""
    if name.split(".")[0] == "opendssdirect" and module != "simulator_bridge.opendss.dss_context":
        return "only simulator_bridge/opendss/dss_context.py imports opendssdirect"
    if module.startswith("adapters.") and name.startswith("simulator_bridge"):
        if not (name.startswith("simulator_bridge.field") or name in ("simulator_bridge", "simulator_bridge.errors")):
            return "adapters use simulator_bridge.field (the device contracts) only"
    if module.startswith("training.") and name.startswith("simulator_bridge.bus"):
        return "training drives OpenDSS through simulator_bridge's engine, never the bus side (simulator_bridge.bus)"
    if module.startswith("simulator_bridge.") and not module.startswith("simulator_bridge.bus") \
            and name.startswith("simulator_bridge.bus"):
        return "only simulator_bridge.bus knows Zenoh: no other room of simulator_bridge imports it"
    return None


def test_every_import_follows_the_layer_table() -> None:
    wrong = []
    for module, names in _all_imports().items():
        pkg = module.split(".")[0]
        for name, line in names:
            top = name.split(".")[0]
            if top in OURS and top != pkg and top not in MAY_IMPORT[pkg]:
                wrong.append(f"{module}:{line} imports {name} ({pkg} may import {sorted(MAY_IMPORT[pkg])})")
            if (why := _narrower(module, name)) is not None:
                wrong.append(f"{module}:{line} imports {name}: {why}")
    assert not wrong, "\n".join(wrong)


def test_no_import_circle_between_modules() -> None:
    """Type-only imports included."""
    graph = {m: sorted({n for n, _ in names if _is_module(n)} - {m}) for m, names in _all_imports(typing=True).items()}
    circles, state = [], dict.fromkeys(graph, 0)  # 0 unseen, 1 on the path, 2 done

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in graph.get(m, ()):
            if state.get(n, 2) == 1:
                circles.append(path[path.index(n):] + [n] if n in path else [m, n])
            elif state.get(n, 2) == 0:
                visit(n, [*path, n])
        state[m] = 2

    for m in graph:
        if state[m] == 0:
            visit(m, [m])
    assert not circles, "\n".join(" -> ".join(c) for c in circles)


@pytest.mark.parametrize("bad", ["simulator_bridge.opendss.engine", "opendssdirect"])
def test_the_rules_catch_a_wrong_import(bad: str) -> None:
    """The check is not vacuous: an adapter importing the engine or OpenDSS is caught."""
    assert _narrower("adapters.sunspec_plant", bad) is not None
    assert _narrower("adapters.cli", "simulator_bridge.field.sunspec_sim") is None
