"""Fuzz the readers of shared files (issue 42, deliverable 8): seeded mutations of a small bundle,
of a small recon folder (its recon.h5 and metrics.json) and of a capture to import (its sidecar
and TIFFs, issue 81), each run through `rngcam inspect` and `rngcam recon` (bundles), `rngcam
inspect` and the report's loader (recon folders) or `rngcam import` and `inspect` (captures).

A case passes when every command ends in a result (exit 0) or one 'error:' line (exit 2), with
no traceback, within TIME_LIMIT_S and with this process's peak resident memory (VmHWM, reset
before each case through /proc/self/clear_refs) under MEMORY_LIMIT_BYTES.

The read-side families (links and special files at every name a reader opens, HDF5 filters and
chunks, text of odd size and shape, checkpoints, calibration files, clip archives) are
bench/fuzz_families.py's; a case of theirs also fails when the reader's secret, which a planted
link points to, shows in any output.

    python -m bench.fuzz OUT_DIR --cases 1200 --seed 0

Cases run in this process, the `rngcam` command loaded as its script loads it (bench.program: a
subprocess per case would spend its time importing torch). Prints
the counts by mutation and outcome and the timings; the figures go in bench/fuzz.md.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import shutil
import signal
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from bench import fuzz_families as families

TIME_LIMIT_S = 10.0
MEMORY_LIMIT_BYTES = 2**30
ODD_STRINGS = ["\x1b[2J\x1b[1;1Herror: forged", "a$b$^{$", "<!--<script>alert(1)</script>", "line\nnext\r",
               "\u202eevil", "x" * 100_000, "", "\x00\x01\x7f", "{\"a\": " * 50, "$$\\frac{", "💥"]
ODD_NUMBERS = [float("nan"), float("inf"), -float("inf"), -1.0, 0.0, 1e308, -1e-308, 2**62, 3.5]
BUNDLE_MUTATIONS = ("truncate", "bitflip", "huge_shape", "wrong_dtype", "nan_inf", "odd_string",
                    "odd_number", "drop", "link", "scale_values")
RECON_MUTATIONS = ("truncate", "bitflip", "huge_shape", "wrong_dtype", "nan_inf", "odd_string", "odd_number",
                   "drop", "link", "metrics_json")
IMPORT_MUTATIONS = ("sidecar_text", "sidecar_field", "truncate", "bitflip", "wrong_shape", "nan_inf", "link")


@dataclass
class Case:
    kind: str  # "bundle", "recon" or "import"
    mutation: str
    seed: int


# ----------------------------------------------------------------------------- mutations


def _objects(f: h5py.File) -> tuple[list[str], list[str]]:
    """Paths of f's datasets and of its objects carrying attributes (root included)."""
    datasets, holders = [], ["/"]
    f.visititems(lambda name, obj: (datasets if isinstance(obj, h5py.Dataset) else holders).append(name))
    return datasets, holders


def _set_attr(obj, name: str, value) -> None:
    with contextlib.suppress(Exception):
        if name in obj.attrs:
            del obj.attrs[name]
    try:
        obj.attrs[name] = value
    except OSError:  # longer than an object header holds (64 KiB without dense storage)
        obj.attrs[name] = value[:16_000] if isinstance(value, bytes) else value


def mutate_h5(path: Path, mutation: str, rng: np.random.Generator, other: Path) -> str:
    """Apply `mutation` to the HDF5 file at `path` in place; returns a short description."""
    data = bytearray(path.read_bytes())
    if mutation == "truncate":
        cut = int(rng.integers(0, len(data)))
        path.write_bytes(bytes(data[:cut]))
        return f"cut at {cut}"
    if mutation == "bitflip":
        n = int(rng.integers(1, 64))
        for pos in rng.integers(0, len(data), n):
            data[pos] ^= 1 << int(rng.integers(0, 8))
        path.write_bytes(bytes(data))
        return f"{n} bits"
    with h5py.File(path, "r+") as f:
        datasets, holders = _objects(f)
        if mutation in ("huge_shape", "wrong_dtype", "nan_inf", "drop", "link", "scale_values") and datasets:
            name = datasets[int(rng.integers(len(datasets)))]
            d = f[name]
            shape, dtype = d.shape, d.dtype
            if mutation == "huge_shape":
                big = tuple(int(rng.choice([1, 7, 8193, 100_000, 2**31])) for _ in range(max(1, len(shape or ()))))
                del f[name]
                f.create_dataset(name, shape=big, dtype=dtype, chunks=tuple(1 for _ in big))
                return f"{name} -> {big}"
            if mutation == "wrong_dtype":
                new = rng.choice(["S4", "c8", "f2", "i1", "?", "compound", "vlen"])
                del f[name]
                if new == "compound":
                    f.create_dataset(name, shape=shape, dtype=np.dtype([("a", "f4"), ("b", "i2")]))
                elif new == "vlen":
                    f.create_dataset(name, shape=shape, dtype=h5py.string_dtype())
                else:
                    f.create_dataset(name, shape=shape, dtype=np.dtype(str(new)))
                return f"{name} -> {new}"
            if mutation == "nan_inf":
                arr = np.asarray(d[()], np.float32) if shape else np.float32(0)
                if arr.size:
                    flat = arr.reshape(-1)
                    flat[rng.integers(0, flat.size, max(1, flat.size // 10))] = rng.choice([np.nan, np.inf, -np.inf])
                del f[name]
                f.create_dataset(name, data=arr)
                return f"{name} NaN/Inf"
            if mutation == "scale_values":
                arr = d[()]
                if np.asarray(arr).dtype.kind in "uif":
                    arr = np.asarray(arr, np.float64) * float(rng.choice([-1.0, 0.0, 1e6, 1e-30, 65536.0]))
                del f[name]
                f.create_dataset(name, data=arr)
                return f"{name} scaled"
            if mutation == "drop":
                del f[name]
                return f"{name} dropped"
            target = rng.choice(["external", "soft", "external_storage"])
            del f[name]
            if target == "external":
                f[name] = h5py.ExternalLink(str(other), "/" + name)
            elif target == "soft":
                f[name] = h5py.SoftLink("/" + datasets[int(rng.integers(len(datasets)))])
            else:
                n = max(1, int(np.prod(shape or (1,))))
                f.create_dataset(name, shape=shape, dtype=dtype,
                                 external=[(str(other), 0, n * max(1, dtype.itemsize))])
            return f"{name} -> {target}"
        obj = f[holders[int(rng.integers(len(holders)))]]
        names = list(obj.attrs) or ["format"]
        attr = names[int(rng.integers(len(names)))]
        if mutation == "odd_string":
            text = ODD_STRINGS[int(rng.integers(len(ODD_STRINGS)))]
            if rng.random() < 0.5:
                _set_attr(obj, attr, np.bytes_(text.encode("utf-8", "surrogatepass")))
            else:  # inside a JSON attribute, where the reader parses it
                _set_attr(obj, attr, np.bytes_(json.dumps({"warnings": [text], "k": text}).encode()))
            return f"{obj.name}@{attr} odd string"
        if mutation == "odd_number":
            _set_attr(obj, attr, ODD_NUMBERS[int(rng.integers(len(ODD_NUMBERS)))])
            return f"{obj.name}@{attr} odd number"
        if attr in obj.attrs:
            del obj.attrs[attr]
        return f"{obj.name}@{attr} dropped"


def mutate_json(path: Path, rng: np.random.Generator) -> str:
    """A mutated metrics.json: truncated, bit-flipped, another type, odd strings or deep nesting."""
    text = path.read_text() if path.is_file() else "{}"
    choice = int(rng.integers(6))
    if choice == 0:
        path.write_text(text[: int(rng.integers(0, len(text) + 1))])
    elif choice == 1:
        data = bytearray(text.encode())
        for pos in rng.integers(0, len(data), 8):
            data[pos] ^= 1 << int(rng.integers(0, 8))
        path.write_bytes(bytes(data))
    elif choice == 2:
        path.write_text(json.dumps(rng.choice(["[]", "3", "null", '"x"'])))
    elif choice == 3:
        m = json.loads(text) if text.startswith("{") else {}
        for k in list(m)[:: max(1, len(m) // 5)]:
            m[k] = ODD_STRINGS[int(rng.integers(len(ODD_STRINGS)))]
        path.write_text(json.dumps(m))
    elif choice == 4:
        path.write_text("[" * 200_000 + "]" * 200_000)
    else:
        m = json.loads(text) if text.startswith("{") else {}
        for k in list(m)[:: max(1, len(m) // 5)]:
            m[k] = float(ODD_NUMBERS[int(rng.integers(len(ODD_NUMBERS)))])
        path.write_text(json.dumps(m))
    return f"metrics.json variant {choice}"


def mutate_capture(folder: Path, mutation: str, rng: np.random.Generator) -> str:
    """A mutated capture to import (capture.yaml and the TIFFs `rngcam export` wrote)."""
    import tifffile
    import yaml

    side = folder / "capture.yaml"
    files = sorted(p for p in folder.glob("*.tif"))
    target = files[int(rng.integers(len(files)))]
    if mutation == "sidecar_text":
        data = bytearray(side.read_bytes())
        for pos in rng.integers(0, len(data), 8):
            data[pos] = int(rng.choice(list(b":-[]{}#&*!|>'\"\n .e9")))
        side.write_bytes(bytes(data))
        return "sidecar text"
    if mutation == "sidecar_field":
        doc = yaml.safe_load(side.read_text())
        part = [k for k in ("rs", "gs", "psf", "calibration", "truth") if isinstance(doc.get(k), dict)]
        section = doc[part[int(rng.integers(len(part)))]]
        key = list(section)[int(rng.integers(len(section)))]
        odd = [*ODD_STRINGS, *ODD_NUMBERS, None, [], [[1.0]], {"a": 1}, [float("nan")] * 3, True]
        section[key] = odd[int(rng.integers(len(odd)))]
        side.write_text(yaml.safe_dump(doc))
        return f"sidecar {key} = odd value"
    if mutation == "truncate":
        target.write_bytes(target.read_bytes()[: int(rng.integers(0, target.stat().st_size))])
    elif mutation == "bitflip":
        data = bytearray(target.read_bytes())
        for pos in rng.integers(0, len(data), 16):
            data[pos] ^= 1 << int(rng.integers(0, 8))
        target.write_bytes(bytes(data))
    elif mutation == "wrong_shape":
        shape = tuple(int(n) for n in rng.integers(1, 9, int(rng.integers(2, 6))))
        tifffile.imwrite(target, np.ones(shape, np.uint16), photometric="minisblack")
    elif mutation == "nan_inf":
        arr = tifffile.imread(target).astype(np.float32)
        arr.flat[rng.integers(0, arr.size, 3)] = [np.nan, np.inf, -np.inf]
        tifffile.imwrite(target, arr, photometric="minisblack")
    else:  # a link in place of the file
        target.unlink()
        target.symlink_to(side)
    return f"{target.name} {mutation}"


# ----------------------------------------------------------------------------- running


def make_seeds(work: Path) -> tuple[Path, Path, Path]:
    """A 16 px simulated bundle, a recon folder of it (blend, one iteration) and its export (a
    capture to import)."""
    from click.testing import CliRunner

    from bench.program import program

    work.mkdir(parents=True, exist_ok=True)
    bundle, folder = work / "seed.h5", work / "seed_recon"
    if not bundle.is_file():
        res = CliRunner().invoke(program(), ["simulate", "sineball", "-o", str(bundle), "--size", "16"])
        assert res.exit_code == 0, res.output
    if not (folder / "recon.h5").is_file():
        shutil.rmtree(folder, ignore_errors=True)
        res = CliRunner().invoke(program(), ["recon", str(bundle), "--method", "blend", "--iters", "1", "-o",
                                        str(folder), "--quiet"])
        assert res.exit_code == 0, res.output
    capture = work / "seed_capture"
    if not (capture / "capture.yaml").is_file():
        from rngcam.formats.bundle import read_bundle
        from rngcam.formats.exporter import export_bundle

        export_bundle(read_bundle(bundle), capture, overwrite=True)
    return bundle, folder, capture


def cases(n: int, seed: int = 0) -> list[Case]:
    """`n` cases: three in ten recon folders, two in ten captures to import, the rest bundles, each
    kind's mutations in turn."""
    out, count = [], Counter()
    for i in range(n):
        kind = "recon" if i % 10 in (0, 3, 6) else "import" if i % 10 in (1, 8) else "bundle"
        kind = families.KIND_SLOTS.get(i % 20, kind)
        mutations = {"recon": RECON_MUTATIONS, "import": IMPORT_MUTATIONS}.get(kind, BUNDLE_MUTATIONS)
        mutations = families.MUTATIONS.get(kind, mutations)
        out.append(Case(kind, mutations[count[kind] % len(mutations)], seed * 1_000_003 + i))
        count[kind] += 1
    return out


def _outcome(res) -> tuple[str, str]:
    """('result' | 'one line' | 'FAILED', detail) of a CliRunner result."""
    out = res.output or ""
    if "Traceback" in out:
        return "FAILED", "traceback in output"
    if res.exit_code == 0:
        return "result", ""
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        return "FAILED", f"{type(res.exception).__name__}: {str(res.exception)[:200]}"
    errors = [ln for ln in out.splitlines() if ln.startswith("error:")]
    if res.exit_code == 2 and len(errors) == 1 and "\x1b" not in out:
        return "one line", errors[0][:200]
    return "FAILED", f"exit {res.exit_code}: {out[-300:]!r}"


class _Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise _Timeout()


def _reset_peak() -> None:
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")


def run_case(case: Case, seeds: tuple[Path, Path], work: Path, measure_memory: bool = True) -> dict:
    """Build the mutated file, run its commands; a row: case, description, outcome, seconds, peak.
    Without `measure_memory` the process's peak is neither reset nor judged (inside a test suite,
    where other tests' peaks are not this case's)."""
    from click.testing import CliRunner

    from bench.program import program
    from rngcam.memory import peak_rss_bytes

    bundle, folder, capture = seeds
    rng = np.random.default_rng(case.seed)
    place = work / f"case{case.seed}"
    shutil.rmtree(place, ignore_errors=True)
    place.mkdir(parents=True)
    read_side = (families.prepare(case, bundle, folder, place, rng, mutate_h5, _load_outcome)
                 if case.kind in families.MUTATIONS else None)
    if read_side is not None:
        target, what, commands, _ = read_side
    elif case.kind == "bundle":
        target = place / "b.h5"
        shutil.copy(bundle, target)
        what = mutate_h5(target, case.mutation, rng, bundle)
        commands = [["inspect", str(target)],
                    ["recon", str(target), "--method", "blend", "--iters", "1", "-o", str(place / "out"), "--quiet"]]
    elif case.kind == "import":
        target = place / "c"
        shutil.copytree(capture, target)
        what = mutate_capture(target, case.mutation, rng)
        commands = [["import", str(target / "capture.yaml"), "-o", str(place / "imported.h5")],
                    ["inspect", str(place / "imported.h5")]]
    else:
        target = place / "r"
        shutil.copytree(folder, target)
        what = (mutate_json(target / "metrics.json", rng) if case.mutation == "metrics_json"
                else mutate_h5(target / "recon.h5", case.mutation, rng, bundle))
        commands = [["inspect", str(target)], ["inspect", str(target), "--json"]]
    if measure_memory:
        _reset_peak()
    start = time.perf_counter()
    outcomes = []
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, TIME_LIMIT_S)
    try:
        for args in commands:
            if args[0] == "inspect" and case.kind == "import" and not (place / "imported.h5").is_file():
                continue  # the import refused: nothing to inspect
            outcomes.append(_outcome(CliRunner().invoke(program(), args)))
        if case.kind == "recon":
            outcomes.append(_load_outcome(target))
        if read_side is not None:
            outcomes += [check() for check in read_side[3]]
    except _Timeout:
        outcomes.append(("FAILED", f"over {TIME_LIMIT_S:g} s"))
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    seconds = time.perf_counter() - start
    peak = peak_rss_bytes()
    if read_side is not None and families.leaked(place, [d for _, d in outcomes]):
        outcomes.append(("FAILED", "the reader's secret is in an output"))
    if measure_memory and peak > MEMORY_LIMIT_BYTES:
        outcomes.append(("FAILED", f"peak memory {peak / 2**20:.0f} MiB"))
    shutil.rmtree(place, ignore_errors=True)
    worst = next((o for o in outcomes if o[0] == "FAILED"), None) or next(
        (o for o in outcomes if o[0] == "one line"), outcomes[0])
    return {"kind": case.kind, "mutation": case.mutation, "seed": case.seed, "what": what,
            "outcome": worst[0], "detail": worst[1], "seconds": seconds, "peak_bytes": peak}


def _load_outcome(folder: Path) -> tuple[str, str]:
    """The report's loader (what `report` and `preview` read) on a recon folder."""
    from rngcam.errors import RngcamError
    from rngcam.recon.report.load import load_run

    try:
        run = load_run(folder)
        np.asarray(run.video[:, :2])
    except RngcamError as exc:
        text = str(exc)
        return ("one line", text[:200]) if "\n" not in text else ("FAILED", "several lines")
    except Exception as exc:  # noqa: BLE001 - what the fuzz is looking for
        return "FAILED", f"load_run: {type(exc).__name__}: {str(exc)[:200]}"
    return "result", ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--cases", type=int, default=1200)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    seeds = make_seeds(args.out / "seeds")
    rows = []
    start = time.perf_counter()
    for i, case in enumerate(cases(args.cases, args.seed)):
        rows.append(run_case(case, seeds, args.out / "cases"))
        if rows[-1]["outcome"] == "FAILED":
            print(f"FAILED {case}: {rows[-1]['what']}: {rows[-1]['detail']}", flush=True)
        if (i + 1) % 100 == 0:
            print(f"{i + 1} cases, {time.perf_counter() - start:.0f} s", flush=True)
    total = time.perf_counter() - start
    (args.out / "fuzz.json").write_text(json.dumps(rows, indent=1))
    by = Counter((r["kind"], r["mutation"], r["outcome"]) for r in rows)
    print(f"\n{len(rows)} cases in {total:.0f} s; outcomes {dict(Counter(r['outcome'] for r in rows))}")
    print("| file | mutation | result | one line | FAILED |\n|---|---|---|---|---|")
    for kind, mutation in sorted({(r["kind"], r["mutation"]) for r in rows}):
        print(f"| {kind} | {mutation} | " + " | ".join(str(by[(kind, mutation, o)])
                                                 for o in ("result", "one line", "FAILED")) + " |")
    secs = np.array([r["seconds"] for r in rows])
    peaks = np.array([r["peak_bytes"] for r in rows]) / 2**20
    print(f"seconds per case: median {np.median(secs):.2f}, max {secs.max():.2f}; "
          f"peak RSS: median {np.median(peaks):.0f} MiB, max {peaks.max():.0f} MiB")
    return 1 if any(r["outcome"] == "FAILED" for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
