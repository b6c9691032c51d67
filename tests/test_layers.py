"""The import graph of rngcam, read with `ast` (nothing is imported): layers only point down, no
package or module imports itself round a loop, and no module reaches for another package's
private names. docs/design.md ("Layers") explains the order below.
"""

from __future__ import annotations

import ast
import textwrap
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "rngcam"

# Floor to top. A unit (a package under rngcam/, or a top-level module) may import units of
# its own layer or below; "rngcam" is the package's own __init__ (the Python API's names, loaded
# from `api` on first use, and `version`'s __version__).
LAYERS = (
    ("version", "errors", "untrusted", "h5safe", "paths", "memory", "cpu", "pixels", "backends"),
    ("physics", "config"),
    ("formats", "video_plan"),
    ("sim",),
    ("acquire",),
    ("calibrate",),
    ("recon",),
    ("api",),
    ("sweeps", "evaluate"),
    ("cli", "rngcam", "__main__", "viewers"),
)


def module_files(root: Path) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is a package __init__) for every .py under `root`."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        if is_package:
            parts.pop()
        out[".".join(parts)] = (path, is_package)
    return out


def imports(root: Path) -> dict[str, set[tuple[str, str | None]]]:
    """Module -> {(imported module, name imported from it or None)}, within root's package."""
    top = root.name
    modules = module_files(root)
    graph: dict[str, set[tuple[str, str | None]]] = defaultdict(set)
    for name, (path, is_package) in modules.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                graph[name] |= {(a.name, None) for a in node.names if a.name.split(".")[0] == top}
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if is_package else name.split(".")[:-1]
                    base = base[:len(base) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != top:
                    continue
                for alias in node.names:
                    sub = f"{target}.{alias.name}"
                    graph[name].add((sub, None) if sub in modules else (target, alias.name))
    return graph


def unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one member (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    nodes = set(edges) | {w for ws in edges.values() for w in ws}
    for start in sorted(nodes):
        if start in index:
            continue
        work = [(start, iter(sorted(edges.get(start, ()))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    component = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        component.append(w)
                        if w == v:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def violations(root: Path, layers=LAYERS) -> dict[str, list[str]]:
    """Every breach of the rules in the module doc, by rule."""
    graph = imports(root)
    level = {u: i for i, layer in enumerate(layers) for u in layer}
    found: dict[str, list[str]] = defaultdict(list)
    module_edges: dict[str, set[str]] = defaultdict(set)
    unit_edges: dict[str, set[str]] = defaultdict(set)
    for module, targets in sorted(graph.items()):
        for target, name in sorted(targets, key=str):
            a, b = unit(module), unit(target)
            if target != module:
                module_edges[module].add(target)
            if a == b:
                continue
            unit_edges[a].add(b)
            for u in (a, b):
                if u not in level:
                    found["no layer"].append(f"{u} (in {module}) has no place in LAYERS")
            if a in level and b in level and level[b] > level[a]:
                found["points up"].append(f"{module} imports {target} ({a} is below {b})")
            private = [p for p in target.split(".")[1:] + ([name] if name else []) if _is_private(p)]
            if private:
                found["private"].append(f"{module} imports {target}{'.' + name if name else ''} "
                                        f"(private to {b})")
    found["package cycle"] = [" <-> ".join(c) for c in cycles(unit_edges)]
    found["module cycle"] = [" <-> ".join(c) for c in cycles(module_edges)]
    return {rule: sorted(set(v)) for rule, v in found.items() if v}


def test_rngcam_layers_only_point_down():
    assert violations(ROOT) == {}


def test_the_graph_sees_imports_inside_functions_and_the_names_imported():
    graph = imports(ROOT)
    assert ("rngcam.acquire.scpi", "SerialTransport") in graph["rngcam.acquire.fake_generator"]  # in a function
    assert ("rngcam.formats.bundle", "Bundle") in graph["rngcam.acquire.capture"]
    assert ("rngcam.version", "__version__") in graph["rngcam.cli"]
    assert ("rngcam.api", None) in graph["rngcam"]  # the package's lazy re-export of the API


def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "toy"
    for rel, text in {"__init__.py": "", **files}.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return root


TOY_LAYERS = (("toy", "low"), ("high",))


def test_a_clean_synthetic_package_passes(tmp_path):
    root = _package(tmp_path, {
        "low/__init__.py": "", "low/a.py": "def f():\n    return 1\n",
        "high/__init__.py": "", "high/b.py": "from toy.low.a import f\nfrom . import c\n",
        "high/c.py": "from toy.high import _helpers\n", "high/_helpers.py": "",
    })
    assert violations(root, TOY_LAYERS) == {}


@pytest.mark.parametrize("files, rule, needle", [
    ({"low/a.py": "def f():\n    from toy.high.b import g\n"}, "points up", "toy.low.a imports toy.high.b"),
    ({"low/a.py": "import toy.high.b\n", "high/b.py": "from toy.low import a\n"}, "package cycle", "high <-> low"),
    ({"high/b.py": "from toy.low.a import _secret\n"}, "private", "toy.low.a._secret"),
    ({"high/b.py": "import toy.low._inner\n", "low/_inner.py": ""}, "private", "toy.low._inner"),
    ({"high/b.py": "from . import c\n", "high/c.py": "from .b import x\n"}, "module cycle",
     "toy.high.b <-> toy.high.c"),
    ({"extra/__init__.py": "", "extra/d.py": "from toy.low import a\n"}, "no layer", "extra"),
])
def test_a_planted_violation_is_caught(tmp_path, files, rule, needle):
    base = {"low/__init__.py": "", "low/a.py": "", "high/__init__.py": "", "high/b.py": "", "high/c.py": ""}
    found = violations(_package(tmp_path, {**base, **files}), TOY_LAYERS)
    assert rule in found, found
    assert any(needle in line for line in found[rule]), found[rule]


# Inside recon, floor to top: the pipeline's parts that methods stand on (the problem, the loop and
# its checkpoint and guard, settings fields, noise, metrics, held-out scoring, output writers); the
# learned networks; the methods; the pipeline that runs a method (registry, run settings, runner,
# its log, result, report page).
RECON_LAYERS = (
    ("problem", "gridding", "ablation", "defects", "loop", "checkpoint", "phases", "options", "noise", "metrics",
     "metrics_schema", "misfit", "holdout", "outputs"),
    ("nets",),
    ("methods",),
    ("registry", "settings", "runner", "runlog", "result", "report"),
)
# Packages recon must never import, whatever their layer: a reconstruction reads bundles, not devices.
RECON_NEVER_IMPORTS = ("rngcam.acquire", "rngcam.calibrate")


def recon_violations(root: Path = ROOT) -> list[str]:
    """Imports inside rngcam.recon that point up RECON_LAYERS, or out to RECON_NEVER_IMPORTS."""
    level = {u: i for i, layer in enumerate(RECON_LAYERS) for u in layer}
    found = []
    for module, targets in sorted(imports(root).items()):
        if not module.startswith("rngcam.recon."):
            continue
        a = module.split(".")[2]
        for target, _ in sorted(targets, key=str):
            if target.startswith(RECON_NEVER_IMPORTS):
                found.append(f"{module} imports {target} (recon never imports acquire or calibrate)")
            if not target.startswith("rngcam.recon."):
                continue
            b = target.split(".")[2]
            for u in (a, b):
                if u not in level:
                    found.append(f"recon.{u} (in {module}) has no place in RECON_LAYERS")
            if a in level and b in level and level[b] > level[a]:
                found.append(f"{module} imports {target} (recon.{a} is below recon.{b})")
    return sorted(set(found))


def test_recon_is_laid_out_by_concern_and_never_reaches_for_devices():
    assert recon_violations() == []


def test_recon_layers_catch_a_planted_breach(tmp_path):
    root = tmp_path / "rngcam"
    for rel, text in {"__init__.py": "", "recon/__init__.py": "", "recon/loop.py": "",
                      "recon/nets/__init__.py": "", "recon/nets/net.py": "from rngcam.recon.methods import m\n",
                      "recon/methods/__init__.py": "", "recon/methods/m.py": "import rngcam.acquire.capture\n",
                      "acquire/__init__.py": "", "acquire/capture.py": ""}.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    found = recon_violations(root)
    assert any("rngcam.recon.nets.net imports rngcam.recon.methods" in f for f in found), found
    assert any("never imports acquire" in f for f in found), found
