"""Choose beta/tau/psi without ground truth: a grid of fits scored on held-out measurements.

Every setting of the grid is a trial: fit on the training split of the bundle's measurements
(Problem.with_holdout), scored by the relative residual on the held-out split
(rngcam.recon.holdout); with `folds` > 1, on that many splits, scored by the mean. Poor
trials stop early by synchronous successive halving: rung r gives
every live trial budget B / eta^(R-1-r) (iterations and/or seconds; the last rung gets the full
budget B) and keeps the best 1/eta by held-out score; trials resume from their checkpoints, so
a longer rung continues a shorter one. The decisions depend only on the scores, so a Ray run and
an in-process run of an iteration budget give the same table.

The best setting by held-out score at the last rung is refitted on all measurements with
rngcam.api.reconstruct (outputs in <out>/best/). Outputs: sweep.csv, sweep.md,
sweep.png (held-out score and, with truth, PSNR per trial), sweep.json. Each trial's result
is cached under <out>/trials/<key>/ keyed by bundle checksum, method, settings, split and
budget: re-running skips finished trials (delete a trial's folder to redo it).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rngcam.api import reconstruct
from rngcam.errors import ConfigError, RngcamError
from rngcam.formats.bundle import bundle_checksum, read_bundle
from rngcam.recon import registry
from rngcam.recon.metrics_schema import check_metrics
from rngcam.recon.options import check_seconds
from rngcam.recon.problem import build_problem
from rngcam.sweeps import tables
from rngcam.sweeps.backend import Backend, make_backend
from rngcam.sweeps.trial import TRUTH_KEYS, TrialSpec, run_trial
from rngcam.untrusted import load_json, read_untrusted, replacing, write_new

SCORE_KEYS = ("heldout", "heldout_rs", "heldout_gs", "residual_rs", "residual_gs")
DEFAULT_TIME_BUDGET_S = 30.0


@dataclass
class SweepSettings:
    method: str = "stfm"
    grid: dict[str, list[float]] = field(default_factory=dict)  # parameter -> values
    preset: str | None = None  # the method's preset (None: its default)
    time_budget_s: float | None = None  # per trial at the full budget (None with max_iters: none)
    max_iters: int | None = None  # per trial at the full budget
    holdout: float = 0.2  # fraction of RS row bins held out to score the trials
    holdout_gs: float = 0.0  # fraction of GS pixels also held out (see rngcam.recon.holdout)
    holdout_seed: int = 0
    folds: int = 3  # held-out splits per trial (one fit each, blocks at other places); the score is their mean
    eta: int = 3  # successive halving: keep the best 1/eta at each rung
    rungs: int | None = None  # None: as many as the grid size supports, at most 3
    device: str = "cpu"
    grid_bin: int | None = None
    refit: bool = True

    def __post_init__(self):
        entry = registry.get(self.method)
        if not entry.iterative:
            raise ConfigError(f"sweep needs a fitted method ({', '.join(registry.names(registry.ITERATIVE))}), "
                              f"not {self.method!r}")
        unknown = sorted(set(self.grid) - set(entry.sweepable()))
        if unknown:
            raise ConfigError(f"cannot sweep {', '.join(unknown)} of {self.method}; "
                              f"sweepable: {', '.join(entry.sweepable())}")
        for name, values in self.grid.items():
            if not values:
                raise ConfigError(f"--{name} needs at least one value")
            for v in values:
                if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                    raise ConfigError(f"--{name} values must be finite and >= 0, got {v!r}")
        if self.time_budget_s is None and self.max_iters is None:
            self.time_budget_s = DEFAULT_TIME_BUDGET_S
        if self.time_budget_s is not None:
            check_seconds("time_budget_s", self.time_budget_s)
        if self.max_iters is not None and self.max_iters < 1:
            raise ConfigError(f"iterations per trial must be >= 1, got {self.max_iters}")
        if not 0 < self.holdout < 1:
            raise ConfigError(f"holdout must be a fraction in (0, 1), got {self.holdout}")
        if not 0 <= self.holdout_gs < 1:
            raise ConfigError(f"GS holdout must be a fraction in [0, 1), got {self.holdout_gs}")
        if self.folds < 1:
            raise ConfigError(f"folds must be >= 1, got {self.folds}")
        if self.eta < 2:
            raise ConfigError(f"eta must be >= 2, got {self.eta}")
        if self.rungs is not None and self.rungs < 1:
            raise ConfigError(f"rungs must be >= 1, got {self.rungs}")
        entry.settings(self.preset)  # an unknown preset is one ConfigError line


def setting_grid(grid: dict[str, list[float]]) -> list[dict[str, float]]:
    """Every combination, parameters in alphabetical order (the last one varies fastest)."""
    names = sorted(grid)
    return [dict(zip(names, combo)) for combo in itertools.product(*(grid[n] for n in names))]


def default_rungs(n_trials: int, eta: int) -> int:
    """1 + floor(log_eta(n)), at most 3: every rung keeps at least one trial."""
    rungs = 1
    while rungs < 3 and n_trials >= eta ** rungs:
        rungs += 1
    return rungs


def rung_budgets(settings: SweepSettings, rungs: int) -> list[tuple[int | None, float | None]]:
    """(max_iters, time_budget_s) of each rung, growing by eta up to the full budget."""
    out = []
    for r in range(rungs):
        shrink = settings.eta ** (rungs - 1 - r)
        iters = None if settings.max_iters is None else max(1, round(settings.max_iters / shrink))
        secs = None if settings.time_budget_s is None else settings.time_budget_s / shrink
        out.append((iters, secs))
    return out


def default_out_dir(bundle_path: Path, method: str) -> Path:
    return bundle_path.with_name(f"{bundle_path.stem}-sweep-{method}")


def _key(payload: dict) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()[:16]


def _budget_tag(iters: int | None, secs: float | None) -> str:
    return "-".join(([f"it{iters}"] if iters is not None else []) + ([f"s{secs:g}"] if secs is not None else []))


@dataclass
class SweepResult:
    rows: list[dict]
    best: dict
    out_dir: Path
    backend: str
    new_runs: int  # trial-rungs fitted by this call
    cached_runs: int  # trial-rungs read from earlier runs
    refit: dict | None = None  # the refit's metrics.json
    refit_skipped: bool = False


def _plan_trials(settings: SweepSettings, out: Path, checksum: str) -> list[dict]:
    """Every setting of the grid as a trial: its number, values, options, key and folder (keyed by
    what it fits on, not by budget, so a later rung continues it)."""
    base = {"bundle_sha256": checksum, "method": settings.method, "holdout": settings.holdout,
            "holdout_gs": settings.holdout_gs, "holdout_seed": settings.holdout_seed, "folds": settings.folds,
            "grid_bin": settings.grid_bin}
    trials = []
    for i, values in enumerate(setting_grid(settings.grid)):
        options = dict(values) if settings.preset is None else {**values, "preset": settings.preset}
        key = _key({**base, "options": options})
        trials.append({"trial": i + 1, "values": values, "options": options, "key": key,
                       "dir": out / "trials" / key})
    return trials


def sweep(bundle_path: str | Path, out_dir: str | Path | None = None, settings: SweepSettings | None = None,
          backend_factory: Callable[[], Backend] | None = None, trial_fn=run_trial,
          echo: Callable[[str], None] = print) -> SweepResult:
    """Run the sweep described in the module docstring; returns its table and choice.

    `backend_factory` makes the backend when there is work (default: Ray when installed, else
    in-process); `trial_fn(spec, problem) -> dict` is `run_trial` unless a test wraps it.
    """
    settings = settings or SweepSettings()
    bundle_path = Path(bundle_path)
    out = Path(out_dir) if out_dir is not None else default_out_dir(bundle_path, settings.method)
    checksum = bundle_checksum(bundle_path)
    trials = _plan_trials(settings, out, checksum)
    rungs = settings.rungs or default_rungs(len(trials), settings.eta)
    budgets = rung_budgets(settings, rungs)
    out.mkdir(parents=True, exist_ok=True)

    state = {"problem": None, "backend": None}

    def problem():
        if state["problem"] is None:
            state["problem"] = build_problem(read_bundle(bundle_path), grid_bin=settings.grid_bin)
        return state["problem"]

    def backend() -> Backend:
        if state["backend"] is None:
            state["backend"] = (backend_factory or (lambda: make_backend(echo=echo)))()
            echo(f"trials run on {state['backend'].name}")
        return state["backend"]

    last: dict[int, dict] = {}
    reached: dict[int, int] = {}
    alive = list(range(len(trials)))
    new_runs = cached_runs = 0
    try:
        for r, (iters, secs) in enumerate(budgets):
            tag = _budget_tag(iters, secs)
            todo = []
            for i in alive:
                cached = _load_cached(trials[i]["dir"] / f"result-{tag}.json")
                if cached is not None:
                    last[i] = cached
                    cached_runs += 1
                else:
                    todo.append(i)
            if todo:
                p = problem()
                b = backend()
                entry = registry.get(settings.method)
                specs = [TrialSpec(key=trials[i]["key"], method=settings.method,
                                   settings=entry.settings(settings.preset, **trials[i]["values"]),
                                   max_iters=iters, time_budget_s=secs, trial_dir=str(trials[i]["dir"]),
                                   holdout_rs=settings.holdout, holdout_gs=settings.holdout_gs,
                                   seed=settings.holdout_seed, folds=settings.folds, device=settings.device,
                                   threads=b.threads_per_task) for i in todo]
                echo(f"rung {r + 1}/{rungs} ({tag}): {len(todo)} trial(s) to fit, "
                     f"{len(alive) - len(todo)} already done")

                def finished(j: int, res: dict, r=r, todo=todo, tag=tag) -> None:
                    t = trials[todo[j]]
                    echo(f"  rung {r + 1}/{rungs} trial {t['trial']} {_describe(t['values'])}: {_summary(res)}")
                    if "key" in res:  # came back from the trial itself (not a lost worker): keep it now
                        _save_cached(t["dir"] / f"result-{tag}.json", res)

                results = b.map(trial_fn, specs, p, on_result=finished)
                for i, res in zip(todo, results):
                    last[i] = res
                    new_runs += 1
            for i in alive:
                reached[i] = r + 1
            ok = sorted((i for i in alive if last[i].get("status") == "ok"), key=lambda i: (_score(last[i]), i))
            alive = ok[:math.ceil(len(alive) / settings.eta)] if r < rungs - 1 else ok
    finally:
        if state["backend"] is not None:
            state["backend"].close()

    if not alive:
        messages = sorted({last[i].get("message", "") for i in last if last[i].get("status") != "ok"})
        raise RngcamError(f"every trial failed ({'; '.join(m for m in messages if m)[:300]}); "
                          f"see {out / 'trials'}")
    best_i = alive[0]
    rows = _rows(trials, last, reached, rungs, best_i)
    has_truth = any("psnr_db" in last[i] for i in last)
    _write_outputs(out, rows, has_truth, settings, bundle_path, checksum, rungs, budgets)
    best = rows[best_i]
    echo(f"best by held-out score: trial {best['trial']} {_describe(trials[best_i]['values'])} "
         f"(held-out {best['heldout']:.4g})")
    result = SweepResult(rows=rows, best=best, out_dir=out, backend=state["backend"].name if state["backend"] else
                         "none (every trial was already done)", new_runs=new_runs, cached_runs=cached_runs)
    if settings.refit:
        result.refit, result.refit_skipped = _refit(bundle_path, out / "best", settings, trials[best_i], echo)
    _write_summary(out / "sweep.json", result, settings, checksum, trials[best_i])
    return result


def _score(res: dict) -> float:
    s = res.get("heldout")
    return math.inf if s is None or not math.isfinite(s) else float(s)


def _describe(values: dict) -> str:
    return " ".join(f"{k}={v:g}" for k, v in values.items()) or "(defaults)"


def _summary(res: dict) -> str:
    if res.get("status") != "ok":
        return f"failed: {res.get('message', '')}"
    text = f"held-out {res['heldout']:.4g}, {res.get('iterations', 0)} it, {res.get('seconds', 0):.1f} s"
    if "psnr_db" in res:
        text += f", PSNR {res['psnr_db']:.2f} dB"
    return text


def _load_cached(path: Path) -> dict | None:
    """A trial's cached result, or None (missing, unreadable, too large or deep, not a dict of a
    result's types, or a link, FIFO or device someone planted: read by descriptor, never blocking)."""
    try:
        data = load_json(read_untrusted(path, 1 << 20, what="trial result"), str(path))
    except RngcamError:
        return None
    return data if isinstance(data, dict) and _result_types_ok(data) else None


def _result_types_ok(data: dict) -> bool:
    """True when a cached result's fields that the sweep computes with have their types."""
    numbers = (*SCORE_KEYS, *TRUTH_KEYS, "iterations", "seconds")
    number_ok = all(data.get(k) is None or (isinstance(data[k], (int, float)) and not isinstance(data[k], bool))
                    for k in numbers)
    return number_ok and all(isinstance(data.get(k, ""), str) for k in ("status", "message", "key"))


def _read_metrics(out: Path) -> dict | None:
    """`out`/metrics.json, every field of its type; None when absent or unreadable (then refit)."""
    try:
        text = read_untrusted(out / "metrics.json", 16 << 20, what="metrics.json", within=out)
        return check_metrics(load_json(text, str(out / "metrics.json")), str(out / "metrics.json"))
    except (RngcamError, ValueError):
        return None


def _save_cached(path: Path, res: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_new(path, json.dumps({k: v for k, v in res.items() if k != "traceback"}, default=float))


def _swept(rows: list[dict]) -> list[str]:
    """The swept settings: a row's keys other than the table's fixed columns."""
    fixed = {"trial", "rungs", "iterations", "seconds", "status", "key", "note", *SCORE_KEYS, *TRUTH_KEYS}
    return [k for k in rows[0] if k not in fixed] if rows else []


def _rows(trials: list[dict], last: dict, reached: dict, rungs: int, best_i: int) -> list[dict]:
    rows = []
    for i, t in enumerate(trials):
        res = last.get(i, {})
        row = {"trial": t["trial"], **t["values"], "rungs": reached.get(i, 0),
               "iterations": res.get("iterations"), "seconds": res.get("seconds"),
               **{k: res.get(k) for k in SCORE_KEYS + TRUTH_KEYS}, "status": res.get("status", "not run"),
               "key": t["key"]}
        if res.get("status") != "ok":
            note = res.get("message", "")
        elif i == best_i:
            note = "best (refitted on all measurements)"
        elif reached.get(i, 0) < rungs:
            note = f"stopped early after rung {reached[i]}/{rungs}"
        else:
            note = ""
        row["note"] = note
        rows.append(row)
    return rows


def _columns(rows: list[dict], has_truth: bool) -> list[str]:
    swept = _swept(rows)
    scores = [k for k in SCORE_KEYS if any(r.get(k) is not None for r in rows)]
    truth = [k for k in TRUTH_KEYS if has_truth and any(r.get(k) is not None for r in rows)]
    return ["trial", *swept, "rungs", "iterations", "seconds", *scores, *truth, "status", "note"]


def _write_outputs(out: Path, rows: list[dict], has_truth: bool, settings: SweepSettings, bundle_path: Path,
                   checksum: str, rungs: int, budgets: list) -> None:
    cols = _columns(rows, has_truth)
    tables.write_csv(out / "sweep.csv", rows, cols + ["key"])
    budget_text = ", ".join(_budget_tag(*b) for b in budgets)
    head = (f"# Sweep of {settings.method} on {bundle_path.name}\n\n"
            f"Bundle sha256 `{checksum[:16]}...`; held out: {settings.holdout:g} of the RS row bins, "
            f"{settings.holdout_gs:g} of the GS pixels, {settings.folds} fold(s), seed {settings.holdout_seed}; "
            f"successive halving, {rungs} rung(s), eta {settings.eta}, budgets "
            f"{budget_text}. Scores are relative residuals on held-out measurements (lower is better)"
            f"{'; PSNR is against the bundle truth, never used to choose' if has_truth else ''}.\n\n")
    fmt = {"seconds": lambda v: "-" if v is None else f"{v:.1f}",
           "psnr_db": lambda v: "-" if v is None else f"{v:.2f}",
           "psnr_intermediate_db": lambda v: "-" if v is None else f"{v:.2f}"}
    tables.write_text(out / "sweep.md", head + tables.markdown(rows, cols, fmt))
    plot_sweep(out / "sweep.png", rows, has_truth, f"{settings.method} on {bundle_path.name}")


def plot_sweep(png_path: Path, rows: list[dict], has_truth: bool, title: str = "") -> None:
    """Held-out score per trial (filled: reached the last rung) and, with truth, PSNR per trial."""
    import matplotlib  # heavy: matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: matplotlib

    swept = _swept(rows)
    labels = [", ".join(f"{p}={r[p]:g}" for p in swept) or f"trial {i + 1}" for i, r in enumerate(rows)]
    x = list(range(len(rows)))
    full = max((r["rungs"] for r in rows), default=0)
    fig, ax = plt.subplots(figsize=(max(6.0, 0.55 * len(rows) + 2), 4.2))
    for i, r in enumerate(rows):
        s = r.get("heldout")
        if s is None or not math.isfinite(s):
            continue
        done = r["rungs"] == full and r["status"] == "ok"
        ax.plot(i, s, "o", color="C0", mfc="C0" if done else "none")
    best = [i for i, r in enumerate(rows) if r["note"].startswith("best")]
    for i in best:
        ax.plot(i, rows[i]["heldout"], "*", color="C3", ms=14, label="chosen")
    ax.set(ylabel="held-out relative residual (filled: full budget)", yscale="log", title=title,
           xlabel="trial (swept settings: " + (", ".join(swept) or "none") + ")")
    ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
    if has_truth:
        ax2 = ax.twinx()
        ax2.plot(x, [r.get("psnr_db") if r.get("psnr_db") is not None else math.nan for r in rows],
                 "s--", color="C1", ms=4, label="PSNR vs truth")
        ax2.set_ylabel("PSNR (dB)", color="C1")
        ax2.legend(loc="lower right", fontsize=7, framealpha=0.6)
    if best:
        ax.legend(loc="lower left", fontsize=7, framealpha=0.6)
    fig.tight_layout()
    with replacing(png_path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


def _refit(bundle_path: Path, out: Path, settings: SweepSettings, trial: dict,
           echo: Callable[[str], None]) -> tuple[dict, bool]:
    """Refit the chosen setting on every measurement; skipped when already done for it."""
    marker = out / "sweep-refit.json"
    stamp = {"key": trial["key"], "max_iters": settings.max_iters, "time_budget_s": settings.time_budget_s}
    if _load_cached(marker) == stamp and (metrics := _read_metrics(out)) is not None:
        echo(f"refit of the chosen setting already in {out}")
        return metrics, True
    echo(f"refitting {_describe(trial['values'])} on all measurements into {out}")
    t0 = time.perf_counter()
    result = reconstruct(bundle_path, settings.method, out=out, progress=echo, bar=False,
                         time_budget_s=settings.time_budget_s, max_iters=settings.max_iters, device=settings.device,
                         grid_bin=settings.grid_bin, overwrite=True,
                         method_settings=registry.get(settings.method).settings(settings.preset, **trial["values"]))
    if result.status == "failed":
        raise RngcamError(f"{result.message}; outputs from the last good state are in {out}")
    metrics = result.metrics
    echo(f"refit done in {time.perf_counter() - t0:.1f} s" +
         (f", PSNR {metrics['psnr_db']:.2f} dB" if "psnr_db" in metrics else ""))
    _save_cached(marker, stamp)
    return metrics, False


def _write_summary(path: Path, result: SweepResult, settings: SweepSettings, checksum: str, best: dict) -> None:
    summary = {"bundle_sha256": checksum, "settings": asdict(settings), "backend": result.backend,
               "new_runs": result.new_runs, "cached_runs": result.cached_runs,
               "best": {"trial": best["trial"], "options": best["options"], "key": best["key"],
                        **{k: result.best.get(k) for k in SCORE_KEYS + TRUTH_KEYS if result.best.get(k) is not None}},
               "refit": result.refit, "refit_skipped": result.refit_skipped}
    tables.write_text(path, json.dumps(summary, indent=2, default=float))
