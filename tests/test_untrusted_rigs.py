"""A rig from elsewhere is untrusted: it cannot load native code the user did not name, a
producer that crashes on load is one line, its paths stay where it says (`package:` inside
rngcam/data, calibration writes inside its folder) and its text reaches the terminal as text."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from rngcam.acquire import libraries
from rngcam.acquire.resolve import resolve_psf_path, resolve_rig
from rngcam.cli import main
from rngcam.config import load_rig
from rngcam.errors import ConfigError
from rngcam.paths import DATA_DIR, MEASURED_PSF, resolve_data_ref

REPO = Path(__file__).resolve().parents[1]
MOCK_TEXT = (REPO / "rigs" / "mock.yaml").read_text()
MARKER_C = r"""
#include <stdio.h>
__attribute__((constructor)) static void ran(void) {
    FILE *f = fopen(MARKER, "w");
    if (f) { fputs("constructor ran\n", f); fclose(f); }
}
"""
CRASH_C = r"""
#include <signal.h>
__attribute__((constructor)) static void crash(void) { raise(SIGSEGV); }
"""
ENV = (libraries.ALLOW_ENV, libraries.GENTL_ENV, libraries.CTI_ENV)


@pytest.fixture(autouse=True)
def _nothing_allowed(monkeypatch):
    for name in ENV:
        monkeypatch.delenv(name, raising=False)
    libraries._probed.clear()  # each test probes its own libraries afresh


@pytest.fixture(scope="module")
def libs(tmp_path_factory):
    """Two tiny shared libraries: one whose constructor writes a marker file, one whose
    constructor raises SIGSEGV (a bogus GenTL producer)."""
    if shutil.which("gcc") is None:
        pytest.skip("gcc is not installed: the test builds its own shared libraries")
    d = tmp_path_factory.mktemp("libs")
    marker = d / "constructor-ran"
    built = {}
    for name, source, defines in (("marker", MARKER_C, [f'-DMARKER="{marker}"']), ("crash", CRASH_C, [])):
        (d / f"{name}.c").write_text(source)
        out = d / f"{name}.so"
        subprocess.run(["gcc", "-shared", "-fPIC", *defines, "-o", str(out), str(d / f"{name}.c")], check=True)
        built[name] = out
    loads = subprocess.run([sys.executable, "-c", "import ctypes, sys; ctypes.CDLL(sys.argv[1])", str(built["marker"])],
                           capture_output=True, text=True)
    if loads.returncode != 0 or not marker.is_file():  # e.g. a temporary folder mounted noexec
        pytest.skip(f"a shared library built in {d} cannot be loaded here: {loads.stderr.strip()[-200:]}")
    marker.unlink()
    return {**built, "marker_file": marker}


def _rig_file(folder: Path, cti: Path | None = None, visa_library: Path | None = None,
              name: str = "shared") -> Path:
    """A genicam rig (cameras.*.cti) or a pylon rig on a VISA generator (generator.visa_library)."""
    cams = {"backend": "genicam", "cti": f'"{cti}"'} if cti else {"backend": "pylon"}
    extra = ", ".join(f"{k}: {v}" for k, v in cams.items())
    generator = (f'{{dialect: keysight_33500b, transport: visa, visa_resource: "USB0::1::2::3::INSTR", '
                 f'visa_library: "{visa_library}"}}' if visa_library else
                 '{dialect: keysight_33500b, transport: serial, port: "/dev/rngcam-no-such-port"}')
    text = f"""
name: {name}
cameras:
  rs: {{{extra}, serial: "1", pixel_format: Mono8, exposure_s: 650.0e-6,
        roi: {{width: 32, height: 32}}, line_time_s: 208.0e-6, trigger: {{channel: 1}}}}
  gs: {{{extra}, serial: "2", pixel_format: Mono8, exposure_s: 650.0e-6,
        roi: {{width: 32, height: 32}}, trigger: {{channel: 2}}}}
timing: {{gs_trigger_s: [0.0, 6.5e-3, 13.0e-3]}}
generator: {generator}
calibration: {{psf: {{path: "package:{MEASURED_PSF}", crop: 0.25}}}}
"""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "rig.yaml"
    path.write_text(text)
    return path


COMMANDS = {
    "capture": lambda rig, out: ["capture", "--rig", str(rig), "-o", str(out / "x.h5")],
    "calibrate linetime": lambda rig, out: ["calibrate", "linetime", "--rig", str(rig)],
    "devices --rig": lambda rig, out: ["devices", "--rig", str(rig)],
}


def _run(args: list[str]):
    result = CliRunner().invoke(main, args)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result


def _one_error_line(result) -> str:
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert lines[-1].startswith("error: ") and "Traceback" not in result.output
    return lines[-1]


@pytest.mark.parametrize("command", list(COMMANDS))
def test_a_rig_cannot_load_a_producer_the_user_did_not_name(tmp_path, libs, command):
    rig = _rig_file(tmp_path / "rig", cti=libs["marker"])
    before = sorted(p.name for p in tmp_path.rglob("*"))
    line = _one_error_line(_run(COMMANDS[command](rig, tmp_path)))
    assert "cameras.rs.cti" in line and str(libs["marker"]) in line and "--allow-library" in line, line
    assert not libs["marker_file"].exists()  # its constructor never ran, not even in a child
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written


@pytest.mark.parametrize("command", ["capture", "calibrate linetime"])
def test_a_rig_cannot_load_a_visa_library_the_user_did_not_name(tmp_path, libs, command):
    rig = _rig_file(tmp_path / "rig", visa_library=libs["marker"])
    line = _one_error_line(_run(COMMANDS[command](rig, tmp_path)))
    assert "generator.visa_library" in line and str(libs["marker"]) in line and "RNGCAM_ALLOW_LIBRARY" in line
    assert not libs["marker_file"].exists()
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "rig" / "rig.calib.h5").exists()


@pytest.mark.parametrize("command", list(COMMANDS))
def test_an_allowed_producer_that_crashes_on_load_is_one_line(tmp_path, libs, command):
    rig = _rig_file(tmp_path / "rig", cti=libs["crash"])
    line = _one_error_line(_run([*COMMANDS[command](rig, tmp_path), "--allow-library", str(libs["crash"])]))
    assert f"the GenTL producer {libs['crash']} crashed when loaded (signal 11" in line, line


def test_the_environment_allows_a_library_too(tmp_path, libs, monkeypatch):
    rig = _rig_file(tmp_path / "rig", visa_library=libs["crash"])
    monkeypatch.setenv(libraries.ALLOW_ENV, str(libs["crash"]))
    line = _one_error_line(_run(COMMANDS["capture"](rig, tmp_path)))
    assert f"the VISA library {libs['crash']} crashed when loaded (signal 11, SIGSEGV)" in line
    monkeypatch.delenv(libraries.ALLOW_ENV)
    cti_rig = _rig_file(tmp_path / "cti", cti=libs["crash"])
    monkeypatch.setenv(libraries.GENTL_ENV, str(libs["crash"].parent))  # the GenTL folders name it
    line = _one_error_line(_run(COMMANDS["devices --rig"](cti_rig, tmp_path)))
    assert "crashed when loaded (signal 11" in line


def test_vendor_locations_and_visa_specs():
    assert libraries.vendor_location(Path("/opt/pylon/lib/gentlproducer/gtl/ProducerU3V.cti"))
    assert libraries.vendor_location(Path("/usr/lib/x86_64-linux-gnu/libvisa.so.21"))
    assert not libraries.vendor_location(Path("/opt/pylon/../../tmp/evil.cti"))
    assert not libraries.vendor_location(Path("/usr/lib/evil.so"))
    assert not libraries.vendor_location(Path("/tmp/libvisa.so"))
    genicam = pytest.importorskip("genicam", reason="the genicam wheel (viky.cti) is not installed")
    assert libraries.vendor_location(Path(genicam.__file__).parent / "viky.cti")
    for spec in (None, "", "sim", "@py", "@sim", "defs.yaml@sim", "@ivi"):
        assert libraries.visa_library_path(spec) is None, spec
    assert libraries.visa_library_path("/x/lib.so") == Path("/x/lib.so")
    assert libraries.visa_library_path("/x/lib.so@ivi") == Path("/x/lib.so")


def test_devices_lists_the_cameras_of_the_rigs_producer(tmp_path):
    genicam = pytest.importorskip("genicam", reason="the genicam wheel (viky.cti) is not installed")
    cti = Path(genicam.__file__).parent / "viky.cti"
    if not cti.is_file():
        pytest.skip(f"viky.cti not found in the genicam wheel ({cti})")
    rig = _rig_file(tmp_path, cti=cti)
    result = _run(["devices", "--rig", str(rig)])  # no --cti, no $RNGCAM_CTI: the rig's producer
    assert result.exit_code == 0, result.output
    assert "Viky" in result.output and "serial 0" in result.output


@pytest.mark.parametrize("ref", ["package:../..", "package:../paths.py", "package:../../../etc/passwd",
                                 f"package:{DATA_DIR}/../paths.py"])
def test_package_names_stay_inside_the_package_data(tmp_path, ref):
    with pytest.raises(ConfigError, match=r"package:NAME names a file inside .*this one leaves it"):
        resolve_data_ref(ref, tmp_path)
    rig_path = tmp_path / "mock.yaml"
    rig_path.write_text(MOCK_TEXT.replace(f"package:{MEASURED_PSF}", ref))
    with pytest.raises(ConfigError, match="leaves it") as err:
        resolve_psf_path(load_rig(rig_path))
    assert "\n" not in str(err.value)
    assert resolve_data_ref(f"package:{MEASURED_PSF}", tmp_path) == DATA_DIR / MEASURED_PSF


def test_a_rig_reading_outside_its_folder_is_named_in_one_line(tmp_path):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    shutil.copy(DATA_DIR / MEASURED_PSF, outside / "psf.png")
    rig_path = tmp_path / "rigs" / "mock.yaml"
    rig_path.parent.mkdir()
    rig_path.write_text(MOCK_TEXT.replace(f"package:{MEASURED_PSF}", "../elsewhere/psf.png"))
    lines: list[str] = []
    resolve_rig(load_rig(rig_path), lines.append, psf=False)
    warned = [x for x in lines if x.startswith("warning: ")]
    assert len(warned) == 1 and "calibration.psf.path reads" in warned[0], lines
    assert str(outside / "psf.png") in warned[0] and "outside the rig's folder" in warned[0]
    inside = tmp_path / "rigs" / "inside.yaml"
    inside.write_text(MOCK_TEXT)
    lines.clear()
    resolve_rig(load_rig(inside), lines.append, psf=False)
    assert not [x for x in lines if x.startswith("warning: ")]


def _calibration_rig(folder: Path, calib: str) -> Path:
    text = MOCK_TEXT.replace("calibration:\n  psf:", f"calibration:\n  file: {calib}\n  psf:")
    assert text != MOCK_TEXT
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "mock.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("calib", ["../outside.calib.h5", "ABSOLUTE"])
def test_a_rig_cannot_make_calibrate_write_outside_its_folder(tmp_path, calib):
    target = tmp_path / "outside.calib.h5"
    rig = _calibration_rig(tmp_path / "rigs", str(target) if calib == "ABSOLUTE" else calib)
    line = _one_error_line(_run(["calibrate", "linetime", "--rig", str(rig)]))
    assert f"calibration.file: refusing to write {target}" in line and f"-o {target}" in line, line
    assert not target.exists() and sorted(p.name for p in tmp_path.rglob("*")) == ["mock.yaml", "rigs"]
    chosen = _run(["calibrate", "linetime", "--rig", str(rig), "-o", str(target)])  # the user's choice
    assert chosen.exit_code == 0, chosen.output
    assert target.is_file()


def test_a_symlinked_calibration_file_leading_out_is_refused_too(tmp_path):
    rigs = tmp_path / "rigs"
    rigs.mkdir()
    (rigs / "cal.h5").symlink_to(tmp_path / "victim.h5")
    rig = _calibration_rig(rigs, "cal.h5")
    line = _one_error_line(_run(["calibrate", "linetime", "--rig", str(rig)]))
    assert "calibration.file: refusing to write" in line
    assert not (tmp_path / "victim.h5").exists()


def test_a_rigs_strings_reach_the_terminal_escaped(tmp_path):
    """A model name with an erase-line sequence and a newline cannot erase a line or forge one."""
    evil = "Mock\x1b[2K\rforged: all good\nwarning: none"
    rig_path = tmp_path / "mock.yaml"
    text = MOCK_TEXT.replace("name: mock\n", 'name: "mock\\e[2K\\nerror: forged"\n', 1)
    assert text != MOCK_TEXT
    text = text.replace("model: Mock acA5472-17uc (64x64, 208 us line time)", 'model: "Mock\\e[2K\\rforged: all good\\nwarning: none"', 1)
    rig_path.write_text(text)
    assert load_rig(rig_path).config.cameras.rs.model == evil
    listed = _run(["devices", "--rig", str(rig_path), "--backend", "mock"])
    assert listed.exit_code == 0, listed.output
    assert "\x1b" not in listed.output and "\r" not in listed.output
    assert "Mock\\x1b[2K\\rforged: all good\\nwarning: none" in listed.output
    assert not any(x.startswith("warning: none") for x in listed.output.splitlines())
    # an error line naming the rig's text: one line, escaped
    broken = tmp_path / "broken.yaml"
    broken.write_text(text.replace("calibration:\n  psf:", 'calibration:\n  file: "no\\e[2Kfile\\n.h5"\n  psf:'))
    error = _run(["capture", "--rig", str(broken), "-o", str(tmp_path / "x.h5")])
    assert error.exit_code == 2 and "\x1b" not in error.output
    assert error.output.count("\n") == 2, error.output  # "rig: ..." and the error, nothing forged
    assert "no\\x1b[2Kfile\\n.h5" in error.output
