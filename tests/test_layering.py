"""The package's layering, read from the source (every ``import``, including those inside
functions): no import cycles between modules, and the lower layers never import the higher ones
(docs/architecture.md). A new import that breaks a rule fails here, naming file and line."""

from __future__ import annotations

import ast
from pathlib import Path

import jmocap

SRC = Path(jmocap.__file__).resolve().parent

# layer -> module prefixes it may never import (prefixes of dotted names below jmocap.)
FORBIDDEN = {
    "physics": ("methods", "pipeline", "batch", "results", "evaluate", "metrics", "train", "data",
                "cli", "demo", "viz", "export", "weights", "inputs", "nets", "camera"),
    "metrics": ("methods", "pipeline", "batch", "evaluate", "train", "cli", "demo", "weights", "nets"),
    "data": ("methods", "pipeline", "batch", "results", "evaluate", "metrics", "train", "cli", "demo",
             "weights", "nets", "viz", "export"),
    "methods": ("pipeline", "batch", "results", "evaluate", "metrics", "train", "cli", "demo", "viz",
                "export", "weights", "data"),
    "camera": ("methods", "pipeline", "batch", "evaluate", "metrics", "train", "cli", "demo", "data"),
    "model": ("methods", "pipeline", "batch", "evaluate", "metrics", "train", "cli", "demo", "data", "physics"),
    "io": ("methods", "pipeline", "batch", "evaluate", "metrics", "train", "cli", "demo", "data", "physics"),
    "pipeline": ("batch", "evaluate", "train", "cli", "demo"),
    "subject": ("methods", "pipeline", "batch", "results", "evaluate", "metrics", "train", "cli", "demo",
                "weights", "nets", "viz", "export", "physics"),
    "results": ("methods", "pipeline", "batch", "evaluate", "train", "cli", "demo"),
    # scenes (terrain): geometry under the data layer's clips and the metrics
    "scene": ("methods", "pipeline", "batch", "results", "evaluate", "metrics", "train", "cli", "demo",
              "weights", "nets", "viz", "export", "physics", "model"),
    # MuJoCo C simulation of a character (the synthetic ground truth and ``mocon`` share it)
    "simulator": ("methods", "pipeline", "batch", "results", "evaluate", "metrics", "train", "cli", "demo",
                  "weights", "nets", "viz", "export", "data", "inputs"),
    "weights": ("pipeline", "batch", "evaluate", "train", "cli", "demo"),
    "batch": ("evaluate", "train", "cli", "demo"),
    "evaluate": ("batch", "train", "cli", "demo"),
    "train": ("batch", "evaluate", "cli", "demo"),
    "score": ("methods", "pipeline", "batch", "evaluate", "train", "cli", "demo", "weights", "nets"),
    "export": ("methods", "pipeline", "batch", "evaluate", "metrics", "train", "cli", "demo", "weights", "nets"),
    # video input: detection, tracking and clips on the data layer, overlays through viz; the
    # reconstruction between them is the command line's (cli runs jmocap reconstruct's code)
    "video": ("methods", "physics", "nets", "pipeline", "batch", "evaluate", "metrics", "train", "cli", "demo",
              "weights", "losses"),
}
# video input sits with the commands: no other layer imports it (the command line does)
FORBIDDEN = {layer: rules + ("video",) if layer != "video" else rules for layer, rules in FORBIDDEN.items()}


def _module_name(path: Path) -> str:
    rel = path.relative_to(SRC).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imports() -> dict[str, list[tuple[str, int]]]:
    """module (dotted, below jmocap) -> [(imported jmocap module, line)]."""
    out: dict[str, list[tuple[str, int]]] = {}
    for path in sorted(SRC.rglob("*.py")):
        name = _module_name(path)
        found = []
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                mods = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            else:
                continue
            for m in mods:
                if m == "jmocap" or m.startswith("jmocap."):
                    found.append((m.removeprefix("jmocap").lstrip("."), node.lineno))
        out[name] = found
    return out


def _resolve(target: str, modules: set[str]) -> str | None:
    """The module a dotted import names (``jmocap.physics.cholesky`` -> ``physics``)."""
    parts = target.split(".")
    for n in range(len(parts), 0, -1):
        cand = ".".join(parts[:n])
        if cand in modules:
            return cand
    return None


def test_lower_layers_never_import_higher_ones():
    bad = []
    for mod, deps in imports().items():
        layer = mod.split(".")[0]
        rules = FORBIDDEN.get(layer, ())
        for dep, line in deps:
            top = dep.split(".")[0]
            if top in rules and top != layer:
                bad.append(f"src/jmocap/{mod.replace('.', '/')}: line {line} imports jmocap.{dep}")
    assert not bad, "layering broken:\n" + "\n".join(bad)


def test_no_import_cycles_between_modules():
    graph = imports()
    modules = set(graph)
    edges = {m: {r for d, _ in deps if (r := _resolve(d, modules)) and r != m
                 and not m.startswith(r + ".")}  # a package's submodules may import the package
             for m, deps in graph.items()}
    # a package __init__ re-exporting its submodules is not a cycle with them
    cycles, state, stack = [], {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in sorted(edges[m]):
            if n.startswith(m + "."):
                continue
            if state.get(n) == 1:
                cycles.append(" -> ".join(stack[stack.index(n):] + [n]))
            elif n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_the_checker_sees_imports_inside_functions(tmp_path):
    """The reference for the checker itself: a module whose only jmocap import sits in a
    function body is found (the old batch -> cli circle hid behind such imports)."""
    found = imports()["demo"]
    assert any(dep.startswith("batch") for dep, _ in found)  # demo imports batch inside run_demo


def test_the_batch_path_calls_no_lapack():
    """The reconstruction methods, the physics and the batch engine must not call LAPACK-lowered
    linear algebra (``jnp.linalg.cholesky/solve/inv/...``, ``jax.scipy.linalg``): on CPU with the
    batch sharded over host devices (``jmocap reconstruct``'s default: one per core), two such
    calls at once deadlock XLA's thread pool at 0 % CPU (``jmocap.physics.linalg`` says why; the
    per-frame fit of ``trajopt`` and ``pip`` did so until it used ``physics.linalg``)."""
    import re

    src = SRC
    pattern = re.compile(r"(jax\.scipy\.linalg|jnp\.linalg\.(cholesky|solve|inv|eigh|eig|svd|lstsq|qr|det|slogdet)"
                         r"|jax\.numpy\.linalg\.(cholesky|solve|inv|eigh|eig|svd|lstsq|qr|det|slogdet))")
    files = [*sorted((src / "methods").glob("*.py")), *sorted((src / "physics").glob("*.py")), src / "pipeline.py",
             src / "nets.py", src / "model.py"]
    bad = [f"{f.relative_to(src)}:{i}: {line.strip()}" for f in files
           for i, line in enumerate(f.read_text().splitlines(), 1)
           if pattern.search(line) and not line.lstrip().startswith("#") and f.name != "linalg.py"]
    assert not bad, "LAPACK-lowered linear algebra on the batch path:\n" + "\n".join(bad)
