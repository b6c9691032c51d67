"""Reading files from others: links, special files, sizes and swaps end in one line, by descriptor."""

import os
import threading

import pytest

from rngcam.errors import RngcamError
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
    plain = tmp_path / "plain"
    plain.write_text("theirs")
    secret = tmp_path / "secret"
    secret.write_text("the reader's own text")
    stop = threading.Event()

    def swap():
        while not stop.is_set():
            try:
                os.link(plain, tmp_path / "tmp")
                os.replace(tmp_path / "tmp", name)
                os.symlink(secret, tmp_path / "tmp")
                os.replace(tmp_path / "tmp", name)
            except FileExistsError:
                pass

    t = threading.Thread(target=swap)
    t.start()
    seen = set()
    try:
        for _ in range(2000):
            try:
                seen.add(read_untrusted(name, 1000))
            except UntrustedFileError as exc:
                seen.add(str(exc).split(":")[-1].strip())
    finally:
        stop.set()
        t.join()
    assert b"the reader's own text" not in seen
    assert seen <= {b"theirs", "it is a link (only plain files are read)"}
