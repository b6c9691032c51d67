"""How bench scripts run the `rngcam` program without importing its command-line code.

`RNGCAM` runs it in a child (`python -m rngcam`). `program()` is the same command in this
process, loaded through its installed entry point as the `rngcam` script loads it: for a script
whose subject is what the program prints (bench/fuzz.py) and that runs too many short commands
to pay a child's imports on each. Scripts that run methods in this process call the Python API
(rngcam.reconstruct) instead.
"""

from __future__ import annotations

import functools
import sys

RNGCAM = [sys.executable, "-m", "rngcam"]


@functools.cache
def program():
    """The `rngcam` command (a click group), as the installed script gets it."""
    from importlib.metadata import entry_points

    (script,) = entry_points(group="console_scripts", name="rngcam")
    return script.load()


def main(argv: list[str] | None = None) -> int:
    """`python -m bench.program ARGS...`: the `rngcam` command with ARGS, in this process."""
    try:
        program()(args=sys.argv[1:] if argv is None else argv, prog_name="rngcam")
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
