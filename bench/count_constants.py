"""Count what issue 77 asks to keep out of STFM's code: tuning constants outside stage configs,
function-local imports without a reason, and comments carrying a dated figure or tuning history.

    python -m bench.count_constants            # the three counts
    python -m bench.count_constants --list     # ... and every hit, file:line

Constants: numeric literals in rngcam/recon/methods/stfm/*.py other than 0, 1, 2, -1 and 0.5 (and other than
a small index, slice bound or axis, or a figure shown in an f-string), outside
stage_configs.py and presets.py (the places tuning numbers belong) and outside dataclass field defaults
(a config's or the settings' default is where a number is meant to be); and module-level UPPER_CASE
names bound to a number (each listed once, its literal not counted again). Function-local imports: every
`import` inside a function in rngcam/, and how many carry a trailing `# optional:`, `# heavy:` or
`# cycle:` comment. Dated comments: comments in rngcam/recon/ with a figure in dB, a date or tuning
history ("round N", "stop NN", "was X, now Y").
"""

from __future__ import annotations

import argparse
import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STFM = ROOT / "rngcam" / "recon" / "methods" / "stfm"
CONFIG_MODULES = ("stage_configs.py", "presets.py")
PLAIN = {0, 1, 2, -1, 0.5}
REASONS = ("# optional:", "# heavy:", "# cycle:")
DATED = re.compile(r"\d+(\.\d+)?\s*dB\b|\b20\d\d-\d\d-\d\d\b|\bround \d+|\bstop \d+|\bwas [\d.]+.*\bnow [\d.]+", re.I)


def _is_dataclass(node: ast.ClassDef) -> bool:
    for d in node.decorator_list:
        target = d.func if isinstance(d, ast.Call) else d
        if getattr(target, "id", None) == "dataclass" or getattr(target, "attr", None) == "dataclass":
            return True
    return False


def _number(node) -> float | None:
    if isinstance(node, ast.Constant) and type(node.value) in (int, float):
        return node.value
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub) and _number(node.operand) is not None:
        return -_number(node.operand)
    return None


AXIS_CALLS = {"sum", "mean", "amin", "amax", "std", "var", "permute", "reshape", "view", "expand", "flatten",
              "moveaxis", "unsqueeze", "squeeze", "median", "index_select", "transpose", "repeat", "cat", "stack",
              "split", "chunk", "narrow", "flip", "roll", "select", "size", "norm", "all", "any", "min", "max"}


def _display_or_index(node, value, parents) -> bool:
    """A literal that is no tuning: inside an f-string (a percentage, digits shown), or a small integer
    used as an index, a slice bound or an axis (`x[:, 3]`, `.sum((2, 3))`, `dim=3`)."""
    small = isinstance(value, int) and abs(value) <= 4
    child, up = node, parents.get(id(node))
    while up is not None:
        if isinstance(up, ast.JoinedStr):
            return True
        if small and isinstance(up, ast.Subscript) and child is up.slice:
            return True
        if small and isinstance(up, ast.keyword) and up.arg in ("dim", "axis", "dims"):
            return True
        if small and isinstance(up, ast.Call) and getattr(up.func, "attr", None) in AXIS_CALLS:
            return True
        if small and isinstance(up, ast.Compare) and getattr(up.left, "attr", None) == "ndim":
            return True
        if isinstance(up, (ast.stmt, ast.Lambda)):
            return False
        child, up = up, parents.get(id(up))
    return False


def constants(path: Path) -> list[tuple[int, str]]:
    """(line, what) for each tuning-constant candidate in one STFM module."""
    tree = ast.parse(path.read_text())
    skip: set[int] = set()  # ids of literal nodes not to count
    hits: list[tuple[int, str]] = []
    for node in tree.body:  # module-level UPPER_CASE = number (or a tuple of numbers)
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names = [n.id for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)]
            values = [n for n in ast.walk(node.value) if _number(n) is not None] if node.value else []
            if values and names and all(n.isupper() for n in names):
                hits.append((node.lineno, f"{', '.join(names)} = {ast.unparse(node.value)}"))
                skip.update(id(n) for v in values for n in ast.walk(v))
    for node in ast.walk(tree):  # dataclass field defaults
        if isinstance(node, ast.ClassDef) and _is_dataclass(node):
            for item in node.body:
                if isinstance(item, ast.AnnAssign) and item.value is not None:
                    skip.update(id(n) for n in ast.walk(item.value))
    parents = {id(child): node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    for node in ast.walk(tree):
        value = _number(node)
        if value is None or id(node) in skip or value in PLAIN or _display_or_index(node, value, parents):
            continue
        skip.update(id(n) for n in ast.walk(node))  # -3: the USub counted, not its 3 again
        hits.append((node.lineno, f"literal {ast.unparse(node)}"))
    return sorted(hits)


def local_imports(path: Path) -> list[tuple[int, str, bool]]:
    """(line, the import, has a reason comment) for each import inside a function."""
    text = path.read_text()
    lines = text.splitlines()
    out = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for inner in ast.walk(node):
                if isinstance(inner, (ast.Import, ast.ImportFrom)):
                    end = lines[inner.end_lineno - 1]
                    out.append((inner.lineno, ast.unparse(inner), any(r in end for r in REASONS)))
    return sorted(set(out))


def dated_comments(path: Path) -> list[tuple[int, str]]:
    out = []
    with io.StringIO(path.read_text()) as f:
        for tok in tokenize.generate_tokens(f.readline):
            if tok.type == tokenize.COMMENT and DATED.search(tok.string):
                out.append((tok.start[0], tok.string.strip()))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--list", action="store_true", help="print every hit, file:line")
    args = parser.parse_args()
    rel = lambda p: p.relative_to(ROOT)  # noqa: E731
    named = inline = 0
    for path in sorted(STFM.glob("*.py")):
        if path.name in CONFIG_MODULES:
            continue
        hits = constants(path)
        inline += sum(1 for _, what in hits if what.startswith("literal"))
        named += sum(1 for _, what in hits if not what.startswith("literal"))
        if args.list:
            for line, what in hits:
                print(f"const  {rel(path)}:{line}: {what}")
    imports = [(p, *i) for p in sorted((ROOT / "rngcam").rglob("*.py")) for i in local_imports(p)]
    dated = [(p, *d) for p in sorted((ROOT / "rngcam" / "recon").rglob("*.py")) for d in dated_comments(p)]
    if args.list:
        for p, line, what, reason in imports:
            print(f"import {rel(p)}:{line}: {what}{'' if reason else '   (no reason)'}")
        for p, line, what in dated:
            print(f"dated  {rel(p)}:{line}: {what}")
    print(f"numbers in stfm/ outside the stage configs and presets: {inline + named} ({inline} inline literals, "
          f"{named} module-level named constants)")
    print(f"function-local imports in rngcam/: {len(imports)} "
          f"({sum(1 for i in imports if i[3])} with an optional/heavy/cycle reason)")
    print(f"comments in rngcam/recon/ with a dated figure or tuning history: {len(dated)}")


if __name__ == "__main__":
    main()
