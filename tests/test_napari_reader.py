"""The napari reader, called as napari would (get_reader(path) -> reader -> layer-data tuples),
without napari installed: a reconstruction and a bundle come with a channel axis, a time axis in
µs and the GS key frames as their own layer; the npe2 manifest names the function."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.viewers.napari_reader import get_reader

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    root = tmp_path_factory.mktemp("napari")
    res = CliRunner().invoke(main, ["capture", "--rig", str(REPO / "rigs" / "mock.yaml"), "-o", str(root / "m.h5")])
    assert res.exit_code == 0, res.output
    res = CliRunner().invoke(main, ["recon", str(root / "m.h5"), "--method", "blend", "-o", str(root / "b"), "--quiet"])
    assert res.exit_code == 0, res.output
    return root


def _by_name(layers):
    out = {}
    for data, kw, kind in layers:
        assert kind == "image"
        out[kw["name"][0].rsplit(" ", 1)[0]] = (data, kw)
    return out


def test_a_reconstruction_opens_with_channels_time_in_us_and_key_frames(recon):
    for path in (recon / "b" / "recon.h5", recon / "b", [str(recon / "b" / "recon.h5")]):
        reader = get_reader(str(path) if not isinstance(path, list) else path)
        assert callable(reader), path
    layers = _by_name(get_reader(str(recon / "b"))(str(recon / "b")))
    assert set(layers) == {"blend", "GS key frames", "RS image (coded)"}
    video, kw = layers["blend"]
    assert video.shape == (3, 67, 64, 64) and kw["channel_axis"] == 0
    assert kw["name"] == ["blend R", "blend G", "blend B"] and kw["colormap"] == ["red", "green", "blue"]
    assert kw["scale"][0] == pytest.approx(208.0) and kw["translate"][0] == pytest.approx(104.0)  # µs, centres
    keys, kk = layers["GS key frames"]
    assert keys.shape == (3, 3, 64, 64) and kk["channel_axis"] == 0
    assert kk["scale"][0] == pytest.approx(6500.0) and kk["translate"][0] == pytest.approx(325.0)
    with h5py.File(recon / "b" / "recon.h5") as f:
        assert np.array_equal(keys, f["key_frames"][()])
    assert layers["RS image (coded)"][1]["visible"] is False


def test_a_bundle_opens_with_its_truth_and_key_frames_on_one_time_axis(recon):
    layers = _by_name(get_reader(str(recon / "m.h5"))(str(recon / "m.h5")))
    assert set(layers) == {"truth", "GS key frames", "RS frame (raw, coded)"}
    truth, kt = layers["truth"]
    assert truth.shape[:2] == (3, 67) and kt["scale"][0] == pytest.approx(208.0)
    keys, kk = layers["GS key frames"]
    assert keys.shape[:2] == (3, 3) and 0 <= keys.min() and keys.max() <= 1.0
    assert kk["translate"][0] == pytest.approx(325.0) and kk["scale"][0] == pytest.approx(6500.0)


def test_unequal_key_frame_gaps_are_held_on_the_video_frames(recon, tmp_path):
    import shutil

    shutil.copy(recon / "b" / "recon.h5", tmp_path / "recon.h5")
    with h5py.File(tmp_path / "recon.h5", "a") as f:
        f["key_frame_times_s"][...] = [325e-6, 2000e-6, 13325e-6]
    layers = _by_name(get_reader(str(tmp_path))(str(tmp_path)))
    keys, kk = layers["GS key frames"]
    assert keys.shape == (3, 67, 64, 64) and kk["scale"][0] == pytest.approx(208.0)
    with h5py.File(tmp_path / "recon.h5") as f:
        kf = f["key_frames"][()]
    assert np.array_equal(keys[:, 10], kf[:, 1]) and np.array_equal(keys[:, 9], kf[:, 0])  # 1976 µs < 2000 µs < 2184 µs


def test_other_files_are_left_to_other_readers(tmp_path):
    with h5py.File(tmp_path / "x.h5", "w") as f:
        f["a"] = np.zeros(3)
    (tmp_path / "y.txt").write_text("hello")
    assert get_reader(str(tmp_path / "x.h5")) is None and get_reader(str(tmp_path / "y.txt")) is None
    assert get_reader(str(tmp_path)) is None and get_reader([str(tmp_path / "x.h5")] * 2) is None


def test_the_npe2_manifest_names_the_reader_and_ships_with_the_package():
    manifest = yaml.safe_load((REPO / "rngcam" / "viewers" / "napari.yaml").read_text())
    (cmd,) = manifest["contributions"]["commands"]
    module, attr = cmd["python_name"].split(":")
    import importlib

    assert getattr(importlib.import_module(module), attr) is get_reader
    (reader,) = manifest["contributions"]["readers"]
    assert reader["command"] == cmd["id"] and "*.h5" in reader["filename_patterns"] and reader["accepts_directories"]
    project = (REPO / "pyproject.toml").read_text()  # (tomllib is 3.11+; we support 3.10)
    assert '[project.entry-points."napari.manifest"]\nrngcam = "rngcam.viewers:napari.yaml"' in project
    assert '"viewers/napari.yaml"' in project and "\nnapari = [" in project
