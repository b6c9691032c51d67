"""The fuzzer's read-side families (issue 80): links and special files at every name a reader
opens, HDF5 chunk and filter variations (compression bombs, unknown filters), text of odd size
and shape, compressed or lying checkpoint records, NaN/Inf in calibration files and crafted clip
archives. Each function changes files under a case's folder in place and returns a short
description; bench/fuzz.py runs the commands on them.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import zipfile
import zlib
from pathlib import Path

import h5py
import numpy as np

SECRET = "-----BEGIN OPENSSH PRIVATE KEY----- rngcam-fuzz-secret-of-the-reader"
SPECIAL = ("link_secret", "link_devzero", "fifo", "folder", "dangling")
# where the file is named on the command line, a folder is the command's usage error: left out
FILE_SPECIAL = ("link_secret", "link_devzero", "fifo", "dangling")
FILTER_VARIANTS = ("gzip_shuffle_fletcher", "lzf", "scaleoffset", "unknown_filter", "chunk_past_dataset",
                   "gzip_bomb", "lzf_bomb", "gzip_truncated")
TEXT_VARIANTS = ("vlen_huge", "vlen_many", "deep_yaml", "deep_json", "long_yaml")
METRIC_FIELDS = ("method", "status", "psnr_db", "ssim", "seconds", "iterations", "warnings", "events", "notes",
                 "left_out", "misfit", "peak_rss_bytes", "error_visibility", "settings", "method_results")
WRONG_VALUES = ("text", 3, 2.5, True, None, [1, "a"], {"a": [1]}, [{"component": 1}], -1, "[" * 50)
CHECKPOINT_VARIANTS = ("deflated", "size_lie", "local_header_deflated", "truncated", "bitflip", "legacy_pickle",
                       "not_zip", "many_records", "fifo", "link_secret")
CLIP_VARIANTS = ("object_array", "huge_header", "longer_than_header", "wrong_dtype", "three_dims", "no_frames",
                 "truncated", "bitflip", "fifo", "link_secret", "deflate_bomb_member")
CALIBRATION_MUTATIONS = ("truncate", "bitflip", "huge_shape", "wrong_dtype", "nan_inf", "odd_string", "odd_number",
                         "drop", "link", "special_name", "filters")
# kind -> its mutations; the kinds take these of every 20 cases (bench/fuzz.py's cases)
MUTATIONS = {"bundle_file": ("special_name", "filters", "text"),
             "recon_folder": ("special_name", "filters", "metrics_types"),
             "checkpoint": CHECKPOINT_VARIANTS, "calibration": CALIBRATION_MUTATIONS, "clip": CLIP_VARIANTS}
KIND_SLOTS = {4: "bundle_file", 9: "recon_folder", 12: "checkpoint", 15: "calibration", 17: "clip"}
RECON_NAMES = ("recon.h5", "metrics.json", "errors.csv")


def write_secret(work: Path) -> Path:
    """The reader's own file that a planted link points to; it must never appear in any output."""
    path = work / "secret.txt"
    path.write_text(SECRET + "\n")
    return path


def plant_special(path: Path, rng: np.random.Generator, secret: Path, kinds: tuple[str, ...] = SPECIAL) -> str:
    """Replace the file at `path` by a link to the reader's secret or to /dev/zero, a FIFO, a
    folder or a dangling link (one of `kinds`)."""
    kind = kinds[int(rng.integers(len(kinds)))]
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):
        path.unlink()
    if kind == "link_secret":
        path.symlink_to(secret)
    elif kind == "link_devzero":
        path.symlink_to("/dev/zero")
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "folder":
        path.mkdir()
    else:
        path.symlink_to(path.parent / "gone")
    return f"{path.name} -> {kind}"


def _numeric(f: h5py.File) -> list[str]:
    names = []
    f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) and o.dtype.kind in "uif"
                 and o.shape and o.size > 1 else None)
    return names


def mutate_filters(path: Path, rng: np.random.Generator) -> str:
    """A dataset rewritten chunked and filtered: legitimately (gzip, LZF, scale-offset) or as an
    attack (an unknown filter, a chunk far past the dataset, a chunk inflating past its size, a
    cut stream)."""
    variant = FILTER_VARIANTS[int(rng.integers(len(FILTER_VARIANTS)))]
    with h5py.File(path, "r+") as f:
        names = _numeric(f)
        if not names:
            return f"{variant}: no dataset"
        name = names[int(rng.integers(len(names)))]
        data, attrs = f[name][()], dict(f[name].attrs)
        del f[name]
        chunks = tuple(max(1, s // 2) for s in data.shape)
        kw = {"gzip_shuffle_fletcher": dict(compression="gzip", shuffle=True, fletcher32=True),
              "lzf": dict(compression="lzf"), "gzip_bomb": dict(compression="gzip"),
              "gzip_truncated": dict(compression="gzip"), "lzf_bomb": dict(compression="lzf"),
              "scaleoffset": dict(scaleoffset=0 if data.dtype.kind in "ui" else 3),
              "unknown_filter": dict(compression=int(rng.integers(32100, 33000)), allow_unknown_filter=True),
              }.get(variant, {})
        if variant == "chunk_past_dataset":  # one chunk of 64 MiB (zeros, gzip) over a small dataset
            rest = int(np.prod(data.shape[1:])) * data.dtype.itemsize
            big = (max(data.shape[0] + 1, 2**26 // rest), *data.shape[1:])
            d = f.create_dataset(name, shape=data.shape, dtype=data.dtype, maxshape=(None,) * data.ndim,
                                 chunks=big, compression="gzip")
            d.id.write_direct_chunk((0,) * data.ndim, zlib.compress(bytes(int(np.prod(big)) * data.dtype.itemsize)))
        else:
            d = f.create_dataset(name, data=data, chunks=chunks, **kw)
        for k, v in attrs.items():
            d.attrs[k] = v
        nbytes = int(np.prod(chunks)) * data.dtype.itemsize
        if variant in ("gzip_bomb", "gzip_truncated"):
            stream = zlib.compress(b"\0" * min(nbytes * 1000, 2**28), 9)  # about the chunk's size, 1000x inflated
            d.id.write_direct_chunk((0,) * data.ndim, stream if variant == "gzip_bomb" else stream[: len(stream) // 3])
        elif variant == "lzf_bomb":
            src = f.create_dataset("_lzf_src", data=np.zeros(nbytes * 80 + 4096, np.uint8), chunks=True,
                                   compression="lzf")
            raw = src.id.read_direct_chunk((0,))[1]
            d.id.write_direct_chunk((0,) * data.ndim, raw[: max(16, nbytes)])
            del f["_lzf_src"]
    return f"{name} {variant}"


def mutate_text(path: Path, rng: np.random.Generator) -> str:
    """A text attribute of odd size or shape: a variable-length one of 20 MiB (its item size says
    8 bytes), many of them, YAML or JSON nested far deeper than rngcam writes, long YAML."""
    variant = TEXT_VARIANTS[int(rng.integers(len(TEXT_VARIANTS)))]
    with h5py.File(path, "r+") as f:
        holders = ["/"]
        f.visititems(lambda n, o: holders.append(n))
        obj = f[holders[int(rng.integers(len(holders)))]] if variant in ("vlen_huge", "vlen_many") else f
        attr = {"deep_yaml": "rig_yaml", "long_yaml": "rig_yaml", "deep_json": "meta"}.get(
            variant, (list(obj.attrs) or ["format"])[int(rng.integers(max(1, len(obj.attrs))))])
        if attr in obj.attrs:
            del obj.attrs[attr]
        vlen = h5py.string_dtype()
        if variant == "vlen_huge":
            obj.attrs.create(attr, "x" * (20 * 2**20), dtype=vlen)
        elif variant == "vlen_many":
            obj.attrs.create(attr, np.array(["y" * 1000] * 5000, dtype=object), dtype=vlen)
        elif variant == "deep_yaml":
            obj.attrs.create(attr, "mock:\n  scene: " + "[" * 20_000 + "]" * 20_000, dtype=vlen)
        elif variant == "long_yaml":
            obj.attrs.create(attr, "mock:\n  scene: sineball\n" + "k: [1, 2, 3]\n" * 200_000, dtype=vlen)
        else:
            obj.attrs.create(attr, "[" * 200_000 + "]" * 200_000, dtype=vlen)
    return f"{obj.name}@{attr} {variant}"


def mutate_metrics_types(path: Path, rng: np.random.Generator) -> str:
    """metrics.json with fields of other types (the schema's fields) or nested deeper than allowed."""
    m = json.loads(path.read_text())
    if rng.random() < 0.15:
        m["extra"] = json.loads("[" * 100 + "]" * 100)
        path.write_text(json.dumps(m))
        return "metrics.json nested 100 deep"
    changed = []
    for _ in range(int(rng.integers(1, 4))):
        key = METRIC_FIELDS[int(rng.integers(len(METRIC_FIELDS)))]
        m[key] = WRONG_VALUES[int(rng.integers(len(WRONG_VALUES)))]
        changed.append(key)
    path.write_text(json.dumps(m))
    return f"metrics.json types of {', '.join(changed)}"


# ----------------------------------------------------------------------------- checkpoints


def seed_checkpoint(path: Path) -> Path:
    """A small checkpoint as rngcam's loop writes one (data only), for the checkpoint cases."""
    import torch

    torch.save({"format": 3, "iteration": 1, "solve_s": 0.1, "wall_s": 0.2, "log": [], "events": [],
                "rng": torch.get_rng_state(), "method": {"x": torch.zeros(4096)}, "identity": None}, path)
    return path


def _rezip(data: bytes, compression: int, extra: bytes = b"") -> bytes:
    src, out = zipfile.ZipFile(io.BytesIO(data)), io.BytesIO()
    with zipfile.ZipFile(out, "w", compression) as z:
        for info in src.infolist():
            z.writestr(info.filename, src.read(info) + (extra if info.filename.endswith("/0") else b""))
    return out.getvalue()


def mutate_checkpoint(path: Path, variant: str, rng: np.random.Generator, secret: Path) -> str:
    """A checkpoint whose records are DEFLATE-compressed (a bomb), whose sizes lie, whose local
    header says deflate, cut, bit-flipped, an old pickle, not a zip, 200,000 records, a FIFO or
    a link."""
    data = bytearray(path.read_bytes())
    if variant == "deflated":
        path.write_bytes(_rezip(bytes(data), zipfile.ZIP_DEFLATED, b"\0" * 2**26))
    elif variant in ("size_lie", "local_header_deflated"):
        z = zipfile.ZipFile(io.BytesIO(bytes(data)))
        info = z.infolist()[int(rng.integers(len(z.infolist())))]
        if variant == "size_lie":  # one record's sizes in the central directory, far past the file
            entries = [i for i in range(len(data) - 4) if data[i:i + 4] == b"PK\x01\x02"]
            at = entries[int(rng.integers(len(entries)))]
            data[at + 20:at + 28] = (2**31).to_bytes(4, "little") * 2
        else:
            data[info.header_offset + 8:info.header_offset + 10] = (8).to_bytes(2, "little")
        path.write_bytes(bytes(data))
    elif variant == "truncated":
        path.write_bytes(bytes(data[: int(rng.integers(0, len(data)))]))
    elif variant == "bitflip":
        for pos in rng.integers(0, len(data), int(rng.integers(1, 32))):
            data[pos] ^= 1 << int(rng.integers(0, 8))
        path.write_bytes(bytes(data))
    elif variant == "legacy_pickle":
        path.write_bytes(b"\x80\x02\x8a\nl\xfc\x9cF\xf9 j\xa8P\x19.\x80\x02M\xe9\x03.")
    elif variant == "not_zip":
        path.write_bytes(b"not a checkpoint at all\n" * 10)
    elif variant == "many_records":
        out = io.BytesIO()
        with zipfile.ZipFile(out, "w") as z:
            for i in range(200_000):
                z.writestr(f"archive/data/{i}", b"")
        path.write_bytes(out.getvalue())
    else:
        path.unlink()
        os.mkfifo(path) if variant == "fifo" else path.symlink_to(secret)
    return f"checkpoint {variant}"


# ----------------------------------------------------------------------------- calibration files


def seed_calibration(path: Path) -> Path:
    """A small calibration file as `rngcam calibrate` writes one."""
    from rngcam.formats.calibration import update_calibration

    psf = np.random.default_rng(0).random((1, 16, 16))
    update_calibration(path, rig_name="fuzz", psf=(psf / psf.sum(), {"method": "fuzz"}),
                       gs_to_rs=(np.eye(3), {"method": "fuzz"}), line_time_s=(1e-5, {"method": "fuzz"}),
                       white_balance=(np.ones(1), {"method": "fuzz"}))
    return path


# ----------------------------------------------------------------------------- clip archives


def seed_clip(path: Path) -> Path:
    """An 8-frame 24x24 clip (what `simulate clip --clip` reads)."""
    rng = np.random.default_rng(0)
    np.savez_compressed(path, frames=rng.integers(0, 255, (8, 24, 24, 3), dtype=np.uint8))
    return path


def _npz(path: Path, header: dict, body: bytes, compression: int = zipfile.ZIP_DEFLATED) -> None:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    with zipfile.ZipFile(path, "w", compression) as z:
        z.writestr("frames.npy", buf.getvalue() + body)


def mutate_clip(path: Path, variant: str, rng: np.random.Generator, secret: Path) -> str:
    """A crafted clip archive: a pickled object array, a header declaring far more than is there,
    a member longer than its header says (256 MiB of zeros), another dtype or rank, no frames,
    cut, bit-flipped, a FIFO or a link."""
    base = {"descr": "|u1", "fortran_order": False, "shape": (8, 24, 24, 3)}
    data = bytearray(path.read_bytes())
    if variant == "object_array":
        np.savez(path, frames=np.array([None, {"a": 1}], dtype=object))
    elif variant == "huge_header":
        _npz(path, {**base, "shape": (10**6, 8192, 8192, 3)}, b"\0" * 4096)
    elif variant == "longer_than_header":
        _npz(path, base, b"\0" * (2**28))
    elif variant == "deflate_bomb_member":
        _npz(path, {**base, "shape": (2**14, 1024, 1024, 3)}, b"\0" * 2**28)
    elif variant == "wrong_dtype":
        np.savez(path, frames=np.zeros((8, 24, 24, 3), rng.choice(["f4", "u2", "c8", "?"])))
    elif variant == "three_dims":
        np.savez(path, frames=np.zeros((8, 24, 24), np.uint8))
    elif variant == "no_frames":
        np.savez(path, video=np.zeros((8, 24, 24, 3), np.uint8))
    elif variant == "truncated":
        path.write_bytes(bytes(data[: int(rng.integers(0, len(data)))]))
    elif variant == "bitflip":
        for pos in rng.integers(0, len(data), int(rng.integers(1, 32))):
            data[pos] ^= 1 << int(rng.integers(0, 8))
        path.write_bytes(bytes(data))
    else:
        path.unlink()
        os.mkfifo(path) if variant == "fifo" else path.symlink_to(secret)
    return f"clip {variant}"


def leaked(place: Path, outputs: list[str]) -> bool:
    """True when the reader's secret shows in a command's output or in a file written under `place`."""
    if any(SECRET in (o or "") for o in outputs):
        return True
    for root, _, files in os.walk(place):  # links to folders are not followed
        for name in files:
            p = Path(root) / name
            if p.is_file() and not p.is_symlink() and p.stat().st_size < 2**26:
                with open(p, "rb") as fh:  # our own outputs, regular files checked just above
                    if SECRET.encode() in fh.read():
                        return True
    return False


_EXTRA: dict[Path, dict] = {}


def extra_seeds(work: Path) -> dict:
    """The read-side seeds under `work` (made once): a checkpoint, a calibration file, a clip and
    the reader's secret."""
    if work not in _EXTRA:
        work.mkdir(parents=True, exist_ok=True)
        _EXTRA[work] = {"checkpoint": seed_checkpoint(work / "checkpoint.pt"),
                        "calibration": seed_calibration(work / "cal.h5"), "clip": seed_clip(work / "clip.npz"),
                        "secret": write_secret(work)}
    return _EXTRA[work]


def prepare(case, bundle: Path, folder: Path, place: Path, rng: np.random.Generator, mutate_h5,
            load_outcome) -> tuple[Path, str, list[list[str]], list]:
    """A read-side case's mutated file under `place`: (target, description, commands, checks),
    `checks` being functions that return an outcome (the report's loader)."""
    extra = extra_seeds(place.parent / "_read_side_seeds")
    secret, m = extra["secret"], case.mutation
    if case.kind == "bundle_file":
        target = place / "b.h5"
        shutil.copy(bundle, target)
        what = {"special_name": lambda: plant_special(target, rng, secret, FILE_SPECIAL),
                "filters": lambda: mutate_filters(target, rng), "text": lambda: mutate_text(target, rng)}[m]()
        return target, what, [["inspect", str(target)], ["recon", str(target), "--method", "blend", "--iters", "1",
                                                          "-o", str(place / "out"), "--quiet"]], []
    if case.kind == "recon_folder":
        target = place / "r"
        shutil.copytree(folder, target, symlinks=True)
        if m == "special_name":
            what = plant_special(target / RECON_NAMES[int(rng.integers(len(RECON_NAMES)))], rng, secret)
        elif m == "filters":
            what = mutate_filters(target / "recon.h5", rng)
        else:
            what = mutate_metrics_types(target / "metrics.json", rng)
        commands = [["inspect", str(target)], ["inspect", str(target), "--json"], ["report", str(target)]]
        return target, what, commands, [lambda: load_outcome(target)]
    if case.kind == "checkpoint":
        out = place / "out"
        out.mkdir()
        shutil.copy(extra["checkpoint"], out / "checkpoint.pt")
        what = mutate_checkpoint(out / "checkpoint.pt", m, rng, secret)
        return out, what, [["recon", str(bundle), "--method", "blend", "--iters", "1", "-o", str(out), "--resume",
                            "--quiet"]], []
    if case.kind == "calibration":
        target = place / "cal.h5"
        shutil.copy(extra["calibration"], target)
        what = (plant_special(target, rng, secret, FILE_SPECIAL) if m == "special_name" else mutate_filters(target, rng)
                if m == "filters" else mutate_h5(target, m, rng, bundle))
        return target, what, [["inspect", str(target)]], []
    target = place / "clip.npz"
    shutil.copy(extra["clip"], target)
    what = mutate_clip(target, m, rng, secret)
    return target, what, [["simulate", "clip", "--clip", str(target), "-o", str(place / "s.h5"), "--size", "16",
                           "--span", "4"]], []


def main(argv: list[str] | None = None) -> int:
    """These families are kinds among bench/fuzz.py's cases (`fuzz.cases`): running this runs that fuzzer."""
    from bench.fuzz import main as fuzz_main

    return fuzz_main(argv)


if __name__ == "__main__":
    raise SystemExit(main())
