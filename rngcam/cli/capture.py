"""`rngcam capture` and `rngcam devices`: thin wrappers over rngcam.acquire."""

from __future__ import annotations

import json
import os
import sys
from dataclasses import asdict
from pathlib import Path

import click

from rngcam.acquire import netns
from rngcam.acquire.devices import list_cameras, list_serial_ports
from rngcam.acquire.genicam_camera import CTI_ENV
from rngcam.acquire.libraries import allow, check_rig
from rngcam.backends import CAMERAS
from rngcam.cli import echo_line


def _allow(ctx, param, value):
    if value:
        allow(value)  # into the environment: a rerun in a private network inherits it
    return value


allow_library_option = click.option(
    "--allow-library", multiple=True, type=click.Path(dir_okay=False), expose_value=False, callback=_allow,
    help="Load this native library the rig names (a GenTL producer .cti, a VISA library) although it is "
         "outside the vendors' install locations: it runs code in this process (repeatable; also "
         "$RNGCAM_ALLOW_LIBRARY, ':'-separated).")


def _rerun_in_private_network(rig, args: list[str]) -> None:
    """Simulated GigE cameras are served in a network namespace of their own (loopback only):
    run this same command there and exit with its status."""
    from rngcam.acquire.factory import needs_private_network  # heavy: factory loads cv2, h5py, torch

    if netns.inside() or not needs_private_network(rig):
        return
    echo_line("simulated GigE cameras: running in a private network namespace (loopback only)")
    sys.stdout.flush()
    argv = [sys.executable, "-c", "from rngcam.cli import main; main()", *args]
    raise SystemExit(netns.run_private(argv).returncode)


@click.command("capture")
@click.option("--rig", "rig_path", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Rig file (YAML), e.g. rigs/mock.yaml.")
@click.option("-o", "--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Bundle to write (never overwritten). Default: capture-YYYYmmdd-HHMMSS.h5.")
@click.option("--count", type=click.IntRange(min=1), default=1, show_default=True,
              help="Shots in a row; with N > 1 the names get -001, -002 ...")
@allow_library_option
def capture_cmd(rig_path: Path, out: Path | None, count: int):
    """Trigger the rig's cameras once (or N times) and write a capture bundle."""
    from rngcam.acquire.capture import capture  # heavy: capture loads cv2, h5py, torch
    from rngcam.config import load_rig  # heavy: config loads torch

    rig = load_rig(rig_path)
    echo_line(f"rig: {rig.config.name} ({rig_path})")
    args = ["capture", "--rig", str(rig_path), "--count", str(count)] + (["-o", str(out)] if out else [])
    _rerun_in_private_network(rig, args)
    results = capture(rig, out, count=count, progress=echo_line)
    for r in results:
        echo_line(f"done: {r.path} in {r.seconds['total_s']:.2f} s"
                   + (f" with {len(r.warnings)} warning(s)" if r.warnings else ""))


def _camera_backends() -> list[str]:
    return list(CAMERAS)


@click.command("devices")
@click.option("--backend", type=click.Choice(_camera_backends()), default=None,
              help="Camera backend to list (default: the rig's, else mock plus genicam when a .cti is known).")
@click.option("--cti", type=click.Path(dir_okay=False), default=None,
              help="GenTL producer for the genicam backend (default: $RNGCAM_CTI).")
@click.option("--pylon-tl", "pylon_tl", default=None,
              help="Only this pylon transport layer (e.g. BaslerCamEmu); default: all "
                   "(broadcasts discovery on GigE networks).")
@click.option("--address", "addresses", multiple=True,
              help="aravis: open the camera at this IP address (repeatable); no discovery is sent. "
                   "Without it aravis discovery broadcasts on every interface.")
@click.option("--rig", "rig_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="List this rig's cameras (a simulated rig's are started for it).")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
@allow_library_option
def devices_cmd(backend, cti, pylon_tl, addresses, rig_path, as_json):
    """List cameras (model, serial, interface) and serial ports."""
    from rngcam.config import load_rig  # heavy: config loads torch

    rig = load_rig(rig_path) if rig_path else None
    if rig is not None:
        check_rig(rig)  # the rig's producer is what is listed: a vendor's or one the user named
    if rig is not None and backend in (None, rig.config.cameras.rs.backend):
        _rerun_in_private_network(rig, ["devices", "--rig", str(rig_path)] + (["--backend", backend] if backend else [])
                                  + (["--json"] if as_json else []))
    if backend:
        backends = [backend]
    elif rig is not None:
        backends = [rig.config.cameras.rs.backend]
    else:
        backends = ["mock"] + (["genicam"] if (cti or os.environ.get(CTI_ENV)) else [])
    cameras = []
    for b in backends:
        cameras += list_cameras(b, rig=rig, cti=cti, pylon_transport=pylon_tl, addresses=list(addresses))
    ports = list_serial_ports()
    if as_json:
        click.echo(json.dumps({"cameras": [asdict(c) for c in cameras],
                               "serial_ports": [asdict(p) for p in ports]}, indent=2))
        return
    echo_line(f"cameras ({', '.join(backends)}):")
    if not cameras:
        echo_line("  none found")
    for c in cameras:  # names a device or a rig reports: shown as text
        echo_line(f"  {c.backend:8s} {c.model:28s} serial {c.serial:16s} {c.interface}")
    echo_line("serial ports:")
    if not ports:
        echo_line("  none found")
    for p in ports:
        echo_line(f"  {p.device:16s} {p.description} [{p.hwid}]")
