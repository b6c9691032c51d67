"""bench/ runs the `rngcam` program or calls the library, never imports the command line's code
(issue 38: library code lives below rngcam.cli, where bench/ and the CLI both import it)."""

from __future__ import annotations

import ast
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"


def cli_imports(path: Path) -> list[str]:
    """Each import of rngcam.cli (or of a module under it) in `path`, and each `python -c` string
    that imports it, as 'file:line text'."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and "import" in node.value:
            names = [w.rstrip(";,") for w in node.value.replace("from ", "from\n").split()]
        if any(n == "rngcam.cli" or n.startswith("rngcam.cli.") for n in names):
            found.append(f"{path.name}:{node.lineno} {ast.unparse(node)[:80]}")
    return found


def test_no_bench_script_imports_the_cli():
    scripts = sorted(BENCH.glob("*.py"))
    assert len(scripts) > 10
    assert [hit for path in scripts for hit in cli_imports(path)] == []


def test_the_check_catches_each_way_of_importing_the_cli(tmp_path):
    planted = {
        "a.py": "from rngcam.cli import main\n",
        "b.py": "def f():\n    import rngcam.cli.demo\n",
        "c.py": "from rngcam import cli\n",
        "d.py": "from rngcam.cli.demo import strip_png\n",
        "e.py": "CMD = ['python', '-c', 'from rngcam.cli import main; main()']\n",
    }
    for name, text in planted.items():
        (tmp_path / name).write_text(text)
        assert cli_imports(tmp_path / name), name
    (tmp_path / "ok.py").write_text("from rngcam.evaluate.strips import strip_png\nimport rngcam\n"
                                    "CMD = ['python', '-m', 'rngcam']\n")
    assert cli_imports(tmp_path / "ok.py") == []


def test_python_m_rngcam_runs_the_command(tmp_path):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "rngcam", "--version"], capture_output=True, text=True,
                          cwd=tmp_path, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("rngcam, version ")
