"""Reading files from others: links, special files, sizes and swaps end in one line, by descriptor."""

import json
import os
import threading

import h5py
import numpy as np
import pytest

from rngcam.errors import BundleError, RngcamError
from rngcam.untrusted import UntrustedFileError, open_untrusted, read_untrusted


def test_regular_file_is_read(tmp_path):
    (tmp_path / "a.json").write_bytes(b"{}")
    assert read_untrusted(tmp_path / "a.json", 10) == b"{}"


def test_symlink_at_the_name_is_refused(tmp_path):
    secret = tmp_path / "secret"
    secret.write_text("the reader's own text")
    (tmp_path / "metrics.json").symlink_to(secret)
    with pytest.raises(UntrustedFileError, match="metrics.json: it is a link"):
        read_untrusted(tmp_path / "metrics.json", 1000)


def test_link_in_a_folder_below_the_named_one_is_refused(tmp_path):
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "x").write_text("theirs")
    shared = tmp_path / "shared"
    shared.mkdir()
    (shared / "sub").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(UntrustedFileError, match="it is a link"):
        read_untrusted(shared / "sub" / "x", 100, within=shared)
    assert read_untrusted(shared / "sub" / "x", 100) == b"theirs"  # without `within`: the name only


def test_fifo_neither_blocks_nor_is_read(tmp_path):
    fifo = tmp_path / "errors.csv"
    os.mkfifo(fifo)
    with pytest.raises(UntrustedFileError, match="not a regular file"):
        read_untrusted(fifo, 100)


def test_endless_device_is_refused():
    with pytest.raises(UntrustedFileError, match="not a regular file"):
        read_untrusted("/dev/zero", 100)


def test_folder_and_missing_file(tmp_path):
    with pytest.raises(UntrustedFileError, match="a folder"):
        read_untrusted(tmp_path, 100)
    with pytest.raises(UntrustedFileError, match="not found"):
        read_untrusted(tmp_path / "none", 100)


def test_size_comes_from_the_open_descriptor(tmp_path):
    big = tmp_path / "big"
    big.write_bytes(b"x" * 101)
    with pytest.raises(UntrustedFileError, match="101 bytes, above the limit of 100"):
        read_untrusted(big, 100)


def test_error_class_can_be_the_callers(tmp_path):
    class Mine(RngcamError):
        pass

    with pytest.raises(Mine):
        read_untrusted(tmp_path / "none", 1, error=Mine)


def test_a_file_swapped_after_the_open_is_not_read(tmp_path):
    """The check and the read are on one descriptor: a name swapped for a link in between changes
    nothing that is read."""
    name = tmp_path / "metrics.json"
    name.write_text('{"psnr_db": 30}')
    secret = tmp_path / "secret"
    secret.write_text("the reader's own text")
    with open_untrusted(name, 1000) as fh:
        name.unlink()
        name.symlink_to(secret)
        assert fh.read() == b'{"psnr_db": 30}'


def test_swaps_racing_the_open_never_read_the_linked_file(tmp_path):
    """A name swapped between a regular file and a link to the reader's file, as fast as possible,
    while it is opened: every open reads the regular file or refuses the link in one line."""
    name = tmp_path / "metrics.json"
    secret = tmp_path / "secret"
    secret.write_text("the reader's own text")
    stop = threading.Event()

    def swap():
        while not stop.is_set():
            (tmp_path / "tmp").write_text("theirs")
            os.replace(tmp_path / "tmp", name)
            os.symlink(secret, tmp_path / "tmp")
            os.replace(tmp_path / "tmp", name)

    t = threading.Thread(target=swap)
    t.start()
    seen = set()
    try:
        for _ in range(2000):
            try:
                seen.add(read_untrusted(name, 1000))
            except UntrustedFileError as exc:
                seen.add(str(exc).split(": ", 1)[-1].strip())
    finally:
        stop.set()
        t.join()
    assert b"the reader's own text" not in seen
    link_line = "it is a link (only plain files are read; name the file it points to)"
    assert {s for s in seen if isinstance(s, bytes)} <= {b"theirs"}
    assert {s for s in seen if isinstance(s, str)} <= {link_line, str(name)}  # str(name): 'not found'
    assert b"theirs" in seen or link_line in seen


# --- HDF5 files from others: links, special files, filters, chunks, bombs, text -------------

def _cli(*args):
    from click.testing import CliRunner

    from rngcam.cli import main

    return CliRunner().invoke(main, [str(a) for a in args])


def _one_line(res, *words):
    assert res.exit_code != 0, res.output
    assert "Traceback" not in res.output and res.output.strip().count("\n") == 0, res.output
    assert res.output.startswith("error:"), res.output
    for w in words:
        assert w in res.output, res.output


def _tiny(path):
    from tests.test_untrusted_bundles import tiny_bundle

    return tiny_bundle(path)


def _recompress(path, dataset, **kw):
    """Rewrite `dataset` of the file at `path` chunked and compressed as `kw` says."""
    with h5py.File(path, "r+") as f:
        data = f[dataset][()]
        attrs = dict(f[dataset].attrs)
        del f[dataset]
        d = f.create_dataset(dataset, data=data, **kw)
        for k, v in attrs.items():
            d.attrs[k] = v
        return d.chunks


def test_a_linked_bundle_is_refused_in_one_line(tmp_path):
    own = _tiny(tmp_path / "own.h5")
    (tmp_path / "shot.h5").symlink_to(own)
    _one_line(_cli("inspect", tmp_path / "shot.h5"), "shot.h5", "it is a link")


def test_a_fifo_bundle_neither_blocks_nor_is_read(tmp_path):
    os.mkfifo(tmp_path / "shot.h5")
    _one_line(_cli("inspect", tmp_path / "shot.h5"), "shot.h5")


def test_a_device_bundle_is_refused():
    from rngcam.formats.bundle import read_bundle

    with pytest.raises(BundleError):
        read_bundle("/dev/zero")


def test_an_unknown_hdf5_filter_is_refused_before_hdf5_looks_for_it(tmp_path, monkeypatch):
    shot = _tiny(tmp_path / "shot.h5")
    plugins = tmp_path / "plugins"
    plugins.mkdir()
    monkeypatch.setenv("HDF5_PLUGIN_PATH", str(plugins))
    with h5py.File(shot, "r+") as f:
        f.create_dataset("extra", data=np.zeros(100, "u1"), compression=32015, allow_unknown_filter=True)
    _one_line(_cli("inspect", shot), "shot.h5", "filter 32015", "refused")


def test_the_filters_rngcam_writes_are_read(tmp_path):
    from rngcam.formats.bundle import read_bundle

    for comp in ("gzip", "lzf"):
        shot = _tiny(tmp_path / f"{comp}.h5")
        _recompress(shot, "rs/frames", chunks=(1, 16, 16), compression=comp, shuffle=True, fletcher32=True)
        _recompress(shot, "gs/trigger_times_s", chunks=(2,), scaleoffset=9)
        b = read_bundle(shot)
        assert b.rs.frames.shape == (1, 16, 16) and b.rs.frames.max() > 0


def test_a_chunk_larger_than_its_dataset_is_refused(tmp_path):
    shot = _tiny(tmp_path / "shot.h5")
    with h5py.File(shot, "r+") as f:
        data = f["gs/trigger_times_s"][()]
        del f["gs/trigger_times_s"]
        d = f.create_dataset("gs/trigger_times_s", shape=data.shape, maxshape=(None,), dtype=data.dtype,
                             chunks=(2**18,), compression="gzip")
        d[...] = data
    _one_line(_cli("inspect", shot), "shot.h5", "chunks of", "larger than the dataset")


def _plant_chunk(path, dataset, raw):
    with h5py.File(path, "r+") as f:
        d = f[dataset]
        d.id.write_direct_chunk((0,) * d.ndim, raw)


def test_a_gzip_chunk_that_inflates_past_its_size_is_refused(tmp_path):
    import zlib

    shot = _tiny(tmp_path / "shot.h5")
    _recompress(shot, "rs/frames", chunks=(1, 16, 16), compression="gzip")
    _plant_chunk(shot, "rs/frames", zlib.compress(b"\0" * 2**28, 9)[:400])  # 256 MiB of zeros, cut short
    _one_line(_cli("inspect", shot), "shot.h5", "gzip chunk")
    _plant_chunk(shot, "rs/frames", zlib.compress(b"\0" * 2**20, 9))  # a whole MiB in a 512-byte chunk
    _one_line(_cli("inspect", shot), "shot.h5")


def test_an_lzf_chunk_that_inflates_past_its_size_is_refused(tmp_path):
    shot = _tiny(tmp_path / "shot.h5")
    with h5py.File(tmp_path / "big.h5", "w") as f:  # LZF of 4 MiB of zeros, by h5py's own filter
        big = f.create_dataset("x", data=np.zeros(2**22, "u1"), chunks=(2**22,), compression="lzf")
        raw = big.id.read_direct_chunk((0,))[1]
    _recompress(shot, "rs/frames", chunks=(1, 16, 16), compression="lzf")
    _plant_chunk(shot, "rs/frames", raw[:500])
    _one_line(_cli("inspect", shot), "shot.h5", "LZF chunk")


def test_a_huge_text_attribute_of_variable_length_is_measured_by_its_length(tmp_path):
    shot = _tiny(tmp_path / "shot.h5")
    with h5py.File(shot, "r+") as f:
        del f.attrs["rig_yaml"]
        f.attrs.create("rig_yaml", "a: 1\n" * (4 * 2**20), dtype=h5py.string_dtype())  # 20 MiB, item size 8
    _one_line(_cli("inspect", shot), "shot.h5", "characters of text")


def test_an_hdf5_file_swapped_while_opened_reads_what_was_checked(tmp_path):
    """HDF5 reads the descriptor that was checked: a name swapped for a link to the reader's own
    file right after the check is never read."""
    from rngcam import h5safe

    theirs = _tiny(tmp_path / "shot.h5")
    own = tmp_path / "own.h5"
    with h5py.File(own, "w") as f:
        f.attrs["format"] = "the reader's own"
    real_open = h5safe.open_untrusted_file

    def open_then_swap(path, *a, **kw):
        fh = real_open(path, *a, **kw)
        os.replace(path, tmp_path / "moved.h5")
        os.symlink(own, path)
        return fh

    h5safe.open_untrusted_file = open_then_swap
    try:
        with h5safe.open_untrusted(theirs) as f:
            assert f.attrs["format"] == b"rngcam-bundle"
    finally:
        h5safe.open_untrusted_file = real_open
    assert h5safe.file_format(theirs) == ""  # now a link: refused, not followed


# --- result folders from others: links, special files, types, references, checkpoints ---------

SECRET = "-----BEGIN OPENSSH PRIVATE KEY----- the reader's own"


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """A small recon folder (blend, one iteration) of a simulated bundle with truth."""
    from bench import fuzz

    return fuzz.make_seeds(tmp_path_factory.mktemp("seeds"))


def _copy(folder, tmp_path):
    import shutil

    target = tmp_path / "r"
    shutil.copytree(folder[1], target, symlinks=True)
    (target / "report.html").unlink()
    return target


@pytest.mark.parametrize("name", ["metrics.json", "errors.csv", "recon.h5"])
def test_a_link_in_a_result_folder_is_refused_and_never_shown(folder, tmp_path, name):
    r = _copy(folder, tmp_path)
    secret = tmp_path / "secret"
    secret.write_text(SECRET)
    if name == "recon.h5":
        import shutil

        shutil.move(r / name, secret)  # the reader's own reconstruction
    (r / name).unlink(missing_ok=True)
    (r / name).symlink_to(secret)
    _one_line(_cli("report", r), name, "it is a link")
    if name != "errors.csv":  # inspect reads no errors.csv
        _one_line(_cli("inspect", r), name)
    assert not (r / "report.html").exists()


@pytest.mark.parametrize("name", ["metrics.json", "errors.csv"])
def test_a_fifo_in_a_result_folder_neither_blocks_nor_is_read(folder, tmp_path, name):
    r = _copy(folder, tmp_path)
    (r / name).unlink()
    os.mkfifo(r / name)
    _one_line(_cli("report", r), name, "not a regular file")


@pytest.mark.parametrize("field,value", [("psnr_db", "30"), ("warnings", "one"), ("events", [3]),
                                         ("left_out", [{"component": 1}]), ("misfit", {"line": []}),
                                         ("above_noise", {"line": 3}),
                                         ("peak_rss_bytes", "x"), ("status", 0)])
def test_a_wrong_typed_metrics_field_is_one_line_naming_it(folder, tmp_path, field, value):
    r = _copy(folder, tmp_path)
    m = json.loads((r / "metrics.json").read_text())
    m[field] = value
    (r / "metrics.json").write_text(json.dumps(m))
    _one_line(_cli("report", r), "metrics.json", f"field '{field}")
    _one_line(_cli("inspect", r), "metrics.json", f"field '{field}")


def test_deep_json_in_metrics_is_one_line(folder, tmp_path):
    r = _copy(folder, tmp_path)
    (r / "metrics.json").write_text('{"notes_x": ' + "[" * 100 + "]" * 100 + "}")
    _one_line(_cli("report", r), "metrics.json", "nests deeper")


def test_what_a_run_writes_fits_the_schema_the_readers_check(folder):
    from rngcam.recon.metrics_schema import check_metrics

    m = json.loads((folder[1] / "metrics.json").read_text())
    assert check_metrics(m, "metrics.json") is m and m["method"] == "blend"


def test_a_recorded_bundle_path_is_a_hint_never_a_reason_to_read(folder, tmp_path):
    """recon.h5 naming another bundle: its truth is shown only when its sha256 is the recorded one,
    even with --no-hash-check; a bundle the user names is read."""
    import shutil

    from tests.test_untrusted_bundles import tiny_bundle

    r = _copy(folder, tmp_path)
    other = tmp_path / "other.h5"
    shutil.copy(folder[0], other)
    with h5py.File(other, "a") as f:
        f["truth/video"][...] = 0.123  # another truth, same shape
    with h5py.File(r / "recon.h5", "a") as f:
        f.attrs["bundle_path"] = str(other)
    for extra in ([], ["--no-hash-check"]):
        res = _cli("report", r, *extra)
        assert res.exit_code == 0, res.output
        page = (r / "report.html").read_text()
        assert '"name":"truth"' not in page and "No truth shown" in page, extra
    res = _cli("report", r, "--bundle", folder[0])
    assert res.exit_code == 0, res.output
    assert '"name":"truth"' in (r / "report.html").read_text()
    tiny = tiny_bundle(tmp_path / "tiny.h5")
    with h5py.File(r / "recon.h5", "a") as f:
        f.attrs["bundle_path"] = str(tiny)
    assert _cli("report", r).exit_code == 0 and '"name":"truth"' not in (r / "report.html").read_text()


def _checkpoint(tmp_path):
    import io
    import zipfile

    import torch

    buf = io.BytesIO()
    torch.save({"format": 3, "x": torch.zeros(1000)}, buf)
    return zipfile.ZipFile(io.BytesIO(buf.getvalue()))


def test_a_compressed_checkpoint_record_is_refused_before_torch_reads_it(tmp_path):
    import zipfile

    from rngcam.recon.checkpoint import load

    src = _checkpoint(tmp_path)
    path = tmp_path / "checkpoint.pt"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as out:
        for info in src.infolist():
            out.writestr(info.filename, src.read(info) + (b"\0" * 2**22 if info.filename.endswith("/0") else b""))
    assert path.stat().st_size < 2**20  # 4 MiB of zeros compressed
    with pytest.raises(RngcamError, match=r"cannot resume from .*checkpoint.pt: .*is compressed"):
        load(path)


def test_a_checkpoint_declaring_more_than_it_holds_or_not_a_zip_is_refused(tmp_path):
    from rngcam.recon.checkpoint import load

    path = tmp_path / "checkpoint.pt"
    path.write_bytes(b"\x80\x02}q\x00.")  # a bare pickle: torch's legacy format
    with pytest.raises(RngcamError, match="not a zip archive"):
        load(path)
    os.unlink(path)
    os.mkfifo(path)
    with pytest.raises(RngcamError, match="not a regular file"):
        load(path)


def test_deep_or_huge_yaml_in_a_rig_is_one_line(tmp_path):
    from rngcam.config import load_rig, parse_rig
    from rngcam.errors import ConfigError

    with pytest.raises(ConfigError, match="nested deeper than 64"):
        parse_rig("a: " + "[" * 100 + "]" * 100, tmp_path / "r.yaml")
    with pytest.raises(ConfigError, match="nest"):  # libyaml's own limit, or ours
        parse_rig("a: " + "[" * 50_000 + "]" * 50_000, tmp_path / "r.yaml")
    with pytest.raises(ConfigError, match="characters of YAML"):
        parse_rig("a: " + "x" * 300_000, tmp_path / "r.yaml")
    (tmp_path / "deep.yaml").write_text("- " * 3000 + "x")
    with pytest.raises(ConfigError, match="nested deeper"):
        load_rig(tmp_path / "deep.yaml")
    os.mkfifo(tmp_path / "fifo.yaml")
    with pytest.raises(ConfigError, match="not a regular file"):
        load_rig(tmp_path / "fifo.yaml")


def test_deep_rig_text_in_a_bundle_costs_recon_nothing():
    from rngcam.recon.metrics import one_object_scene

    assert one_object_scene("mock:\n  scene: sineball\n")
    assert not one_object_scene("a: " + "[" * 100_000)


def _npz(path, header_shape, data: bytes, dtype="|u1", compress=True):
    """An .npz whose frames.npy declares `header_shape` of `dtype` over `data`."""
    import zipfile

    header = np.lib.format.header_data_from_array_1_0(np.zeros((1,), np.uint8))
    header.update(shape=tuple(header_shape), descr=dtype)
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED) as z:
        z.writestr("frames.npy", buf.getvalue() + data)
    return path


@pytest.mark.parametrize("case", ["object", "huge_header", "bomb", "fifo", "link", "not_zip", "no_frames"])
def test_a_crafted_clip_archive_is_one_line(tmp_path, case):
    """`simulate --clip` with a crafted .npz: a pickled object array, a header declaring far more
    than the archive holds, 4 GiB of zeros behind a small header, a FIFO, a link, not a zip."""
    from rngcam.sim.scenes import load_clip

    clip = tmp_path / "clip.npz"
    if case == "object":
        np.savez(clip, frames=np.array([None, 1], dtype=object))
    elif case == "huge_header":
        _npz(clip, (10**6, 8192, 8192, 3), b"\0" * 1000)
    elif case == "bomb":
        _npz(clip, (2, 4, 4, 3), b"\0" * 2**28)  # 96 bytes declared, 256 MiB inflated
    elif case == "fifo":
        os.mkfifo(clip)
    elif case == "link":
        np.savez(tmp_path / "own.npz", frames=np.zeros((2, 4, 4, 3), np.uint8))
        clip.symlink_to(tmp_path / "own.npz")
    elif case == "not_zip":
        clip.write_bytes(b"\x93NUMPY" + b"\0" * 100)
    else:
        np.savez(clip, other=np.zeros(3))
    with pytest.raises(RngcamError) as err:
        load_clip(clip)
    assert "clip" in str(err.value) and "\n" not in str(err.value)
    res = _cli("simulate", "clip", "--clip", clip, "-o", tmp_path / "s.h5", "--size", "16")
    _one_line(res, "clip")


def test_the_napari_reader_leaves_links_and_fifos_to_others(folder, tmp_path):
    from rngcam.viewers.napari_reader import get_reader

    assert get_reader(str(folder[1])) is not None
    (tmp_path / "linked.h5").symlink_to(folder[1] / "recon.h5")
    os.mkfifo(tmp_path / "fifo.h5")
    assert get_reader(str(tmp_path / "linked.h5")) is None
    assert get_reader(str(tmp_path / "fifo.h5")) is None


def test_a_file_that_sends_hdf5_into_an_endless_loop_is_one_line(tmp_path, monkeypatch):
    """A global heap object of index 0 and size 0 makes HDF5's parser loop forever when a text
    attribute is read (no signal breaks into it): a forked child reads the metadata first and is
    killed, and the file is refused in one line, once per file."""
    from rngcam import h5safe

    path = tmp_path / "recon.h5"
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "rngcam-recon"
    data = bytearray(path.read_bytes())
    obj = data.find(b"GCOL") + 16
    data[obj:obj + 2] = b"\0\0"
    data[obj + 8:obj + 16] = bytes(8)
    path.write_bytes(bytes(data))
    _one_line(_cli("inspect", path), "recon.h5", "does not finish reading its metadata")

    def no_second_probe():
        raise AssertionError("probed again")

    monkeypatch.setattr(os, "fork", no_second_probe)  # refused from memory after the first probe
    assert h5safe.file_format(path) == ""
    with pytest.raises(RngcamError, match="does not finish"):
        h5safe.open_untrusted(path)
