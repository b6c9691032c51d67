"""bench/ is a package of scripts on the public API: run as `python -m bench.NAME`, none edits
sys.path or imports a private name, and each imports cleanly (its work is behind main())."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"
SCRIPTS = sorted(p for p in BENCH.glob("*.py") if p.name != "__init__.py")


def _private(name: str) -> bool:
    return any(part.startswith("_") and not part.startswith("__") for part in name.split("."))


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: p.stem)
def test_a_bench_script_edits_no_sys_path_and_imports_no_private_name(path):
    text = path.read_text()
    assert "sys.path" not in text
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.ImportFrom) and node.module:
            assert not _private(node.module), node.module
            assert not any(_private(a.name) for a in node.names), [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            assert not any(_private(a.name) for a in node.names), [a.name for a in node.names]


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: p.stem)
def test_a_bench_script_imports_as_part_of_the_package(path):
    module = importlib.import_module(f"bench.{path.stem}")
    assert callable(getattr(module, "main", None))
