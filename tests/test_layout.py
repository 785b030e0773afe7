"""The package's architecture, checked from its sources: no import cycles (counting imports inside
functions), each room imports only the rooms below it, and the estimator never reads truth."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("misrgraph", "factors")

#: Which rooms a room may import (besides itself, ``factors`` and the top-level ``errors`` and
#: ``config`` modules). The data flow of docs/explanation/design.md: model -> misr -> io -> sim / estimate ->
#: products -> evaluate -> runs -> campaign -> bench -> commands (viz beside them, on model, misr and io only).
ALLOWED = {
    "model": set(),
    "misr": {"model"},
    "io": {"model", "misr"},
    "sim": {"model", "misr", "io"},
    "estimate": {"model", "misr", "io"},
    "match": {"model", "misr", "io"},
    "products": {"model", "misr", "io", "estimate", "match"},
    "evaluate": {"model", "misr", "io", "sim", "estimate", "products"},
    "viz": {"model", "misr", "io", "match"},
    "runs": {"model", "misr", "io", "sim", "estimate", "match", "products", "evaluate", "viz"},
    "campaign": {"model", "misr", "io", "sim", "estimate", "match", "products", "evaluate", "viz", "runs"},
    "bench": {"model", "misr", "io", "sim", "estimate", "match", "products", "evaluate", "runs", "campaign"},
    "commands": {
        "model",
        "misr",
        "io",
        "sim",
        "estimate",
        "match",
        "products",
        "evaluate",
        "viz",
        "runs",
        "campaign",
        "bench",
    },
}
BASE = {"misrgraph", "misrgraph.errors", "misrgraph.config", "misrgraph.__main__"}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            rel = p.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


MODULES = _modules()


def _imports(path: Path) -> set[str]:
    """Every package module a file imports, at any depth (module level or inside functions)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for n in names:
            if n in MODULES and n.split(".")[0] in PACKAGES:
                found.add(n)
    return found


GRAPH = {m: _imports(p) - {m} for m, p in MODULES.items()}


def _room(module: str) -> str | None:
    """The room of a module: ``misrgraph.<room>.<module>``, or the room's own package."""
    parts = module.split(".")
    if parts[0] == "misrgraph" and len(parts) == 2 and parts[1] in ALLOWED:
        return parts[1]
    return parts[1] if parts[0] == "misrgraph" and len(parts) > 2 else None


def test_the_import_walk_sees_the_known_edges() -> None:
    # the walk must be able to find edges at all (else the cycle test would pass vacuously)
    assert "misrgraph.model.camera" in GRAPH["misrgraph.model.geolocation"]
    assert "factors.collinearity" in GRAPH["misrgraph.estimate.graph"]


def test_no_import_cycle() -> None:
    """Depth-first search for a back edge over module and function-level imports."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(GRAPH[m]):
            if n.startswith(m + ".") or m.startswith(n + "."):
                continue  # a package and its own submodules
            if state.get(n) == 1:
                cycle = stack[stack.index(n) :] + [n]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(GRAPH):
        if m not in state:
            visit(m)


@pytest.mark.parametrize("module", sorted(m for m in MODULES if _room(m)))
def test_rooms_import_only_rooms_below(module: str) -> None:
    room = _room(module)
    where = "tests/test_layout.py, docs/explanation/design.md"
    assert room in ALLOWED, f"{module}: room {room!r} is not in the layout map ({where})"
    for n in GRAPH[module]:
        other = _room(n)
        if n.split(".")[0] == "factors" or n in BASE or other == room:
            continue
        assert other in ALLOWED[room], f"{module} imports {n}: room {room!r} may use only {sorted(ALLOWED[room])}"


def test_factors_never_import_misrgraph() -> None:
    for m, deps in GRAPH.items():
        if m.startswith("factors"):
            assert not [d for d in deps if d.startswith("misrgraph")], m


def test_model_is_numpy_only() -> None:
    """``misrgraph.model`` and ``misrgraph.misr`` need numpy/scipy (and pyproj, pyerfa, sgp4 for
    frames, orbits and the SOM grid), never gtsam, h5py, rerun or matplotlib."""
    banned = ("gtsam", "h5py", "rerun", "matplotlib", "global_land_mask")
    checked = 0
    for m, p in MODULES.items():
        if _room(m) not in ("model", "misr"):
            continue
        for node in ast.walk(ast.parse(p.read_text())):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""]
                if isinstance(node, ast.ImportFrom)
                else []
            )
            bad = [n for n in names if n.split(".")[0] in banned]
            assert not bad, f"{m} imports {bad}"
        checked += 1
    assert checked >= 10  # both rooms were walked


def test_estimate_never_reads_truth() -> None:
    """No name, attribute, string or argument containing ``truth`` anywhere in the estimator's code
    (docstrings aside), and no import of the simulator or the scoring."""
    for m, p in MODULES.items():
        if _room(m) != "estimate":
            continue
        tree = ast.parse(p.read_text())
        docstrings = {
            id(n.body[0].value)
            for n in ast.walk(tree)
            if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))
            and n.body
            and isinstance(n.body[0], ast.Expr)
            and isinstance(n.body[0].value, ast.Constant)
        }
        for node in ast.walk(tree):
            text = (
                node.id
                if isinstance(node, ast.Name)
                else node.attr
                if isinstance(node, ast.Attribute)
                else node.arg
                if isinstance(node, ast.arg)
                else node.value
                if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings
                else node.name
                if isinstance(node, (ast.FunctionDef, ast.ClassDef))
                else ""
            )
            assert "truth" not in str(text).lower(), f"{m}:{getattr(node, 'lineno', '?')} uses {text!r}"
        for d in GRAPH[m]:
            assert _room(d) not in ("sim", "evaluate"), f"{m} imports {d}"
