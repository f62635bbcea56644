"""The package's layer order holds (DESIGN.md): no import cycles, no module importing
from a layer below its own, no module importing another's private names.

Imports inside functions count as if they were at the top of the module, so a cycle
cannot hide behind a function-level import.
"""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"
#: Top to bottom; a module imports only from its own layer and the layers above it.
LAYERS = ("errors", "version", "atomic", "memory", "geometry", "body", "render", "vision", "fit", "io", "export", "synth",
          "pipeline", "batch", "eval", "viz", "commands", "cli", "__main__")  # __main__: python -m flowmocap


def _modules() -> dict[str, Path]:
    mods = {}
    for p in (SRC / "flowmocap").rglob("*.py"):
        parts = p.relative_to(SRC).with_suffix("").parts
        mods[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return mods


def _imports(mods: dict[str, Path]) -> dict[str, list[tuple[str, str | None, int]]]:
    """``{module: [(imported module, imported name or None, line)]}``, every import in the file."""
    out = {}
    for name, path in mods.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found = []
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found += [(a.name, None, node.lineno) for a in node.names if a.name.startswith("flowmocap")]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                if not base.startswith("flowmocap"):
                    continue
                for a in node.names:
                    sub = f"{base}.{a.name}"
                    found.append((sub, None, node.lineno) if sub in mods else (base, a.name, node.lineno))
        out[name] = found
    return out


def _layer(module: str) -> int:
    parts = module.split(".")
    if len(parts) == 1:
        return len(LAYERS)  # the package itself re-exports the pipeline: nothing inside may import it
    return LAYERS.index(parts[1])


def test_every_module_belongs_to_a_layer():
    for name in _modules():
        if name != "flowmocap":
            assert name.split(".")[1] in LAYERS, f"{name} is in no layer of {LAYERS}; add it in DESIGN.md's order"


def test_no_module_imports_from_a_lower_layer():
    mods = _modules()
    bad = [f"{m}:{line} imports {t}" for m, imps in _imports(mods).items() if m != "flowmocap"
           for t, _, line in imps if _layer(t) > _layer(m)]
    assert not bad, "imports against the layer order:\n" + "\n".join(bad)


def test_no_import_cycles():
    mods = _modules()
    graph = {m: {t for t, _, _ in imps if t in mods and t != m} for m, imps in _imports(mods).items()}
    # a package's __init__ is imported before any of its modules; its own re-exports are not a cycle
    for m in graph:
        graph[m] = {t for t in graph[m] if not (m.startswith(t + ".") and (SRC / Path(*t.split("."))).is_dir())}
    state: dict[str, int] = {}
    cycles = []

    def visit(m, path):
        state[m] = 1
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                cycles.append(" -> ".join(path[path.index(t):] + [t]))
            elif t not in state:
                visit(t, path + [t])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_no_module_imports_another_modules_private_names():
    mods = _modules()
    bad = [f"{m}:{line} imports {t}.{n}" for m, imps in _imports(mods).items()
           for t, n, line in imps if n and n.startswith("_") and not n.startswith("__") and t != m]
    assert not bad, "private names used across modules:\n" + "\n".join(bad)
