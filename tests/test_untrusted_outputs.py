"""A result folder may come from someone else: links (symbolic or hard) planted at its output names
are replaced, never written through, on --resume and --overwrite; `report -o` and `preview -o`
(and the preview's <name>.json) refuse an existing file without --overwrite; --overwrite never
removes the bundle it reads; a bundle's warning is one escaped line in recon.log."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import pytest
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.formats.bundle import read_bundle
from rngcam.formats.bundle_write import write_bundle
from rngcam.recon.checkpoint import CHECKPOINT_NAME, OUTPUT_NAMES

PRECIOUS = "someone else's file\n"
# the names a run wrote through before: its outputs and an older rngcam's fixed temporary names
PLANTED = tuple(dict.fromkeys((*OUTPUT_NAMES, ".metrics.json.partial", "checkpoint.pt.partial")))


def _cli(*args):
    res = CliRunner().invoke(main, [str(a) for a in args])
    return res.exit_code, res.output


def _recon(bundle, out, *extra):
    return _cli("recon", bundle, "--method", "tv3d", "-o", out, "--quiet", *extra)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def folder(shot, tmp_path_factory):
    """A finished tv3d run (2 iterations) on the small capture, copied for each test."""
    out = tmp_path_factory.mktemp("run") / "run"
    code, text = _recon(shot, out, "--iters", "2")
    assert code == 0, text
    return out


def _copy(folder: Path, tmp_path: Path) -> Path:
    out = tmp_path / "run"
    shutil.copytree(folder, out)
    return out


def _plant_links(out: Path, outside: Path, names, hard: tuple[str, ...] = ()) -> dict[Path, str]:
    """A symbolic link at each of `names` (a hard link at those in `hard`) to its own file in
    `outside`; returns each outside file and its content."""
    outside.mkdir(exist_ok=True)
    kept = {}
    for name in names:
        target = outside / f"target-{name.lstrip('.')}"
        target.write_text(PRECIOUS + name)
        kept[target] = target.read_text()
        (out / name).unlink(missing_ok=True)
        if name in hard:
            os.link(target, out / name)
        else:
            (out / name).symlink_to(target)
    return kept


def _assert_untouched(kept: dict[Path, str]) -> None:
    for target, text in kept.items():
        assert target.is_file() and target.read_text() == text, target


def _assert_regular_outputs(out: Path) -> None:
    for name in ("recon.h5", "video.tif", "preview.mp4", "errors.csv", "errors.png", "metrics.json",
                 CHECKPOINT_NAME, "recon.log", "report.html"):
        p = out / name
        assert not p.is_symlink() and p.is_file() and os.stat(p).st_nlink == 1, name
    assert not [p.name for p in out.iterdir() if p.is_symlink()]
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_resume_replaces_links_at_every_output_and_writes_nothing_outside(shot, folder, tmp_path):
    out = _copy(folder, tmp_path)
    names = [n for n in PLANTED if n != CHECKPOINT_NAME]  # the checkpoint itself is the run's own
    kept = _plant_links(out, tmp_path / "outside", names, hard=("recon.log", "video.tif", "errors.csv"))
    code, text = _recon(shot, out, "--resume", "--iters", "3")
    assert code == 0 and "resumed from checkpoint.pt at iteration 2" in text, text
    _assert_untouched(kept)
    _assert_regular_outputs(out)
    assert "resumed from" in (out / "recon.log").read_text()


def test_overwrite_removes_links_and_writes_nothing_outside(shot, folder, tmp_path):
    out = _copy(folder, tmp_path)
    kept = _plant_links(out, tmp_path / "outside", PLANTED, hard=("metrics.json", "errors.png"))
    code, text = _recon(shot, out, "--overwrite", "--iters", "2")
    assert code == 0, text
    _assert_untouched(kept)
    _assert_regular_outputs(out)


def test_temporary_files_left_by_a_killed_run_are_cleaned_by_the_next(shot, folder, tmp_path):
    out = _copy(folder, tmp_path)
    left = out / ".video.tif.abc123.rngcam-tmp"
    left.write_bytes(b"half a file")
    code, text = _recon(shot, out, "--resume", "--iters", "3")
    assert code == 0, text
    assert not left.exists()


@pytest.mark.parametrize("how", ["copy", "link"])
def test_overwrite_or_resume_never_removes_the_bundle_named_like_an_output(shot, tmp_path, how):
    out = tmp_path / "run"
    out.mkdir()
    elsewhere = tmp_path / "bundle.h5"
    shutil.copy(shot, elsewhere)
    if how == "copy":  # the bundle itself sits in the folder under an output's name
        shutil.move(elsewhere, out / "recon.h5")
        bundle = out / "recon.h5"
        original = out / "recon.h5"
    else:  # a link named like an output leads to the bundle
        (out / "video.tif").symlink_to(elsewhere)
        bundle, original = elsewhere, elsewhere
    digest = _sha(original)
    for flag in ("--overwrite", "--resume"):
        code, text = _recon(bundle, out, flag, "--iters", "2")
        lines = text.strip().splitlines()
        assert code == 2 and len(lines) == 1 and "is the bundle this run reads" in lines[0], text
        assert original.is_file() and _sha(original) == digest


def test_report_o_refuses_an_existing_file_without_overwrite(folder, tmp_path):
    page = tmp_path / "page.html"
    page.write_text(PRECIOUS)
    code, text = _cli("report", folder, "-o", page)
    assert code != 0 and "--overwrite" in text and len(text.strip().splitlines()) == 1, text
    assert page.read_text() == PRECIOUS
    # a link at -o's name: refused too, and with --overwrite replaced (what it names is untouched)
    target = tmp_path / "target.txt"
    target.write_text(PRECIOUS)
    link = tmp_path / "link.html"
    link.symlink_to(target)
    code, text = _cli("report", folder, "-o", link)
    assert code != 0 and "--overwrite" in text, text
    code, text = _cli("report", folder, "-o", link, "--overwrite")
    assert code == 0, text
    assert target.read_text() == PRECIOUS and not link.is_symlink() and "<html" in link.read_text().lower()
    code, text = _cli("report", folder, "-o", page, "--overwrite")
    assert code == 0 and "<html" in page.read_text().lower(), text
    # a file the command reads is never replaced, even with --overwrite
    digest = _sha(folder / "recon.h5")
    code, text = _cli("report", folder, "-o", folder / "recon.h5", "--overwrite")
    assert code != 0 and "which this command reads" in text and _sha(folder / "recon.h5") == digest, text


def test_preview_o_and_its_sidecar_refuse_an_existing_file_without_overwrite(folder, tmp_path):
    mp4 = tmp_path / "slow.mp4"
    sidecar = tmp_path / "slow.json"
    sidecar.write_text(PRECIOUS)  # only the sidecar's name is taken
    code, text = _cli("preview", folder, "--fps", "10", "-o", mp4)
    assert code != 0 and f"refusing to replace {sidecar}" in text and len(text.strip().splitlines()) == 1, text
    assert sidecar.read_text() == PRECIOUS and not mp4.exists()
    code, text = _cli("preview", folder, "--fps", "10", "-o", mp4, "--overwrite")
    assert code == 0 and mp4.stat().st_size > 0 and '"frames"' in sidecar.read_text(), text
    size = mp4.stat().st_size
    code, text = _cli("preview", folder, "--fps", "12", "-o", mp4)
    assert code != 0 and f"refusing to replace {mp4}" in text and mp4.stat().st_size == size, text
    digest = _sha(folder / "recon.h5")
    code, text = _cli("preview", folder, "-o", folder / "recon.h5", "--overwrite")
    assert code != 0 and "which this command reads" in text and _sha(folder / "recon.h5") == digest, text


def test_preview_into_its_own_folder_still_replaces_its_own_preview(folder, tmp_path):
    out = _copy(folder, tmp_path)
    target = tmp_path / "outside.mp4"
    target.write_text(PRECIOUS)
    (out / "preview.mp4").unlink()
    (out / "preview.mp4").symlink_to(target)
    code, text = _cli("preview", out, "--fps", "10")
    assert code == 0, text
    assert target.read_text() == PRECIOUS and not (out / "preview.mp4").is_symlink()


def test_a_newline_in_a_bundles_warning_is_one_escaped_line_in_recon_log(shot, tmp_path):
    bundle = read_bundle(shot)
    forged = "12:00:00 error: forged line"
    bundle.meta = {**(bundle.meta or {}), "warnings": [f"loose cable\n{forged}\x1b[2K"]}
    path = write_bundle(bundle, tmp_path / "warned.h5")
    out = tmp_path / "run"
    code, text = _recon(path, out, "--iters", "1")
    assert code == 0, text
    log = (out / "recon.log").read_text().splitlines()
    assert not [line for line in log if line.startswith(forged)], log
    hit = [line for line in log if "loose cable" in line]
    assert len(hit) == 1 and "\\n" + forged in hit[0] and "\\x1b" in hit[0] and "\x1b" not in hit[0], hit


def test_a_folder_at_an_output_name_is_refused_before_anything_is_touched(shot, folder, tmp_path):
    out = _copy(folder, tmp_path)
    (out / "video.tif").unlink()
    (out / "video.tif").mkdir()
    before = {p.name: _sha(p) for p in out.iterdir() if p.is_file()}
    for flag in ("--overwrite", "--resume"):
        code, text = _recon(shot, out, flag, "--iters", "3")
        assert code == 2 and len(text.strip().splitlines()) == 1 and "video.tif is not a file" in text, text
        assert {p.name: _sha(p) for p in out.iterdir() if p.is_file()} == before
