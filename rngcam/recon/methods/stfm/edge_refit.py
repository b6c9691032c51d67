"""Fits again through the PSF with its lost edge fitted, where a fit cannot explain the data.

Self-calibration's key rows find a PSF measured too large (rngcam.recon.methods.selfcal), but
shrunk on the grid it lacks the edge its measurement lost, and applied it never paid. Here the
first fit runs through the PSF as handed; where it stops clearly above its noise level and the
key rows found the PSF too large, its video fits that edge (rngcam.recon.methods.psf_edge), and
where the edge lowers the RS residual by EDGE_MIN_DROP another fit runs through that PSF; then
again from the best fit's video (a better video fits a better edge), at most MAX_REFITS times.
The output is the fit that explains the RS image best (each through its own PSF).
Figures: bench/realistic.md, "A PSF measured too large: its edge fitted".
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from rngcam.recon.loop import MethodBase

# The best fit's RS residual / its noise level at or above which an edge is fitted: where the key
# rows point at a PSF scale (rngcam.recon.misfit.POINTED_RATIO)
EDGE_RATIO = 1.15
EDGE_MAX_SCALE = 0.99  # the key rows' PSF scale at or below which the PSF is taken as measured too large
EDGE_MIN_DROP = 0.15  # the share by which the fitted edge must lower the best video's RS residual
MAX_REFITS = 2  # fits after the first


def edge_scale(selfcal: dict | None) -> float | None:
    """The key rows' PSF scale where it says the PSF was measured too large (not applied, <= EDGE_MAX_SCALE),
    whether or not it lowered their residual: without its edge a shrunk PSF may not (smoke, PSF 5 % large)."""
    psf = ((selfcal or {}).get("scales") or {}).get("psf") or {}
    est = psf.get("estimate")
    if psf.get("applied") or not isinstance(est, float) or not 0 < est <= EDGE_MAX_SCALE:
        return None
    return est


class EdgeRefit(MethodBase):
    """`first` (a whole STFM run) and, where the best fit so far ends unexplained, another through
    the PSF with its edge fitted to that fit's video: `refit(psf, edge_report)` makes such a run."""

    def __init__(self, first, problem, scale: float, refit: Callable):
        self._problem, self._make_refit = problem, refit
        self._flags = (first.supports_holdout, first.stops_itself)  # kept: the first fit may be let go
        self._fits: dict[int, object] = {0: first}  # the current fit and the best so far, by index
        self._psfs: dict[int, Tensor] = {}
        self._current = self._best = 0
        self._rs: dict[int, float] = {}  # each ended fit's RS residual
        self._steps = 0
        self._running: tuple[int, dict] | None = None  # a running later fit's residuals, at that step count
        self.report: dict = {"key_rows_scale": scale, "tried": False, "refits": [], "kept": 0}

    @property
    def _method(self):
        return self._fits[self._current]

    def __getattr__(self, name):  # everything else is the current fit's
        if name.startswith("__") or name in ("_fits", "_current"):
            raise AttributeError(name)
        return getattr(self._method, name)

    @property
    def supports_holdout(self) -> bool:
        return self._flags[0]

    @property
    def stops_itself(self) -> bool:
        return self._flags[1]

    @property
    def left_out(self) -> list:
        return self._method.left_out

    def step(self) -> float:
        self._steps += 1
        return self._method.step()

    def budget_cut(self) -> str:
        return self._method.budget_cut()

    def reduce_step(self, factor: float) -> None:
        self._method.reduce_step(factor)

    def components(self) -> dict:
        return self._output().components()

    def estimate(self) -> Tensor:
        return self._output().estimate()

    def residuals(self) -> dict[str, float]:
        k = self._output_index()
        return self._running[1] if k == self._current and self._running is not None else self._fits[k].residuals()

    def _output(self):
        return self._fits[self._output_index()]

    def _output_index(self) -> int:
        """The fit to show: the current one, unless it has not ended and explains the RS image less
        well than the best so far (a budget that ends a later fit early leaves the best one out)."""
        k = self._current
        if k == self._best or k in self._rs:
            self._running = None
            return k
        if self._running is None or self._running[0] != self._steps:  # once a step, however often asked
            self._running = (self._steps, self._fits[k].residuals())
        res = self._running[1].get("rs")
        return k if isinstance(res, float) and res < self._rs[self._best] else self._best

    def _shown_report(self) -> dict:
        """The report with the fit shown as the one kept (a later fit cut short may be it)."""
        report, k = _copy(self.report), self._output_index()
        if k != report["kept"]:
            report["kept"], report["scale"] = k, report["refits"][k - 1]["scale"]
        return report

    def converged(self) -> str | None:
        why = self._method.converged()
        if why is None or self._rs.get(self._current) is not None:
            return why
        self._ended(self._current)
        if self._next_fit():
            return None
        self._current = self._best  # the output
        return why

    def _ended(self, k: int) -> None:
        """Fit k has stopped: its residual, and whether it is the best so far (the other is let go)."""
        self.report["tried"] = True
        res = self._fits[k].residuals().get("rs")
        self._rs[k] = res = res if isinstance(res, float) and math.isfinite(res) else 1e30  # kept in the state
        if k:
            self.report["refits"][-1]["rs"] = res
        if k == self._best or not res < self._rs[self._best]:
            if k != self._best:
                self._drop(k)
            return
        self._drop(self._best)
        self._best = self.report["kept"] = k
        self.report["scale"] = self.report["refits"][-1]["scale"]

    def _drop(self, k: int) -> None:
        self._fits.pop(k, None)
        self._psfs.pop(k, None)

    def _next_fit(self) -> bool:
        """Fit the edge to the best fit's video; start another fit where it pays."""
        from rngcam.recon.methods.psf_edge import search_edge

        best, res = self._fits[self._best], self._rs[self._best]
        noise = getattr(best, "rs_noise_level", None)
        n = len(self.report["refits"])
        if not noise or not res >= EDGE_RATIO * noise:
            self.report["why"] = (f"the {_nth(self._best)} fit's RS residual is within {EDGE_RATIO}x its noise "
                                  "level" if noise else "no noise level")
            return False
        if n >= MAX_REFITS:
            self.report["why"] = f"{MAX_REFITS} fits through a fitted edge made"
            return False
        if any(r["from_fit"] == self._best for r in self.report["refits"]):  # the same video, the same edge
            self.report["why"] = f"the fit through the edge the {_nth(self._best)} fit's video gave did not do better"
            return False
        self.report["noise_level"] = noise
        with torch.no_grad():
            found = search_edge(self._problem, best.estimate())
        if found is None:
            self.report["why"] = ("no edge could be fitted (on a large grid the edge has more pixels than the RS "
                                  "rows a fit affords can pin: psf_edge.MAX_DESIGN)")
            return False
        drop = 1 - found["residual"] / max(res, 1e-30)
        attempt = {k: v for k, v in found.items() if k not in ("psf", "searched")}
        attempt.update(drop=drop, from_fit=self._best, from_rs=res)
        if not drop >= EDGE_MIN_DROP:
            self.report["why"] = (f"an edge fitted to the {_nth(self._best)} fit's video lowers its RS residual "
                                  f"by {100 * drop:.1f} % (< {100 * EDGE_MIN_DROP:g} %)")
            return False
        self.report["refits"].append(attempt)
        k = n + 1
        self._fits[k], self._psfs[k] = self._make_refit(found["psf"], dict(self.report)), found["psf"]
        self._current = k
        return True

    def state_dict(self) -> dict:
        return {"edge_current": self._current, "edge_best": self._best, "edge_rs": dict(self._rs),
                "edge_report": _copy(self.report), "edge_psfs": dict(self._psfs),
                "fits": {k: fit.state_dict() for k, fit in self._fits.items()}}

    def load_state_dict(self, state: dict) -> None:
        if "fits" not in state:  # a checkpoint of the first fit alone
            self._fits[0].load_state_dict(state)
            return
        _check_state(state, self._problem.psf.shape)
        self.report, self._rs = _copy(state["edge_report"]), dict(state["edge_rs"])
        for k, psf in state["edge_psfs"].items():
            if k not in self._fits:  # a run resumed after its first fit: the later ones made again
                self._fits[k] = self._make_refit(psf, dict(self.report))
            self._psfs[k] = psf
        for k in [k for k in self._fits if k not in state["fits"]]:
            self._drop(k)
        for k, fit_state in state["fits"].items():
            self._fits[k].load_state_dict(fit_state)
        self._current, self._best = state["edge_current"], state["edge_best"]

    @property
    def notes(self) -> list[str]:
        return list(self._output().notes) + ([edge_line(self._shown_report())] if self.report["tried"] else [])

    def resolved_settings(self) -> dict | None:
        out = self._output().resolved_settings()
        out = {} if out is None else dict(out)
        out["psf_edge"] = self._shown_report()
        if isinstance(out.get("self_calibration"), dict):  # the misfit verdict reads it there
            out["self_calibration"] = dict(out["self_calibration"], psf_edge=self._shown_report())
        return out


def _check_state(state: dict, psf_shape) -> None:
    """A checkpoint's edge stage as this class writes it (a checkpoint may come from elsewhere): the
    fitted PSFs of the problem's shape, finite and non-negative, and the fits it names present."""
    from rngcam.errors import RngcamError

    fits, psfs = state.get("fits"), state.get("edge_psfs")
    ok = (isinstance(fits, dict) and isinstance(psfs, dict) and isinstance(state.get("edge_rs"), dict)
          and isinstance(state.get("edge_report"), dict) and 0 in fits
          and state.get("edge_current") in fits and state.get("edge_best") in fits
          and all(isinstance(k, int) and k in psfs for k in fits if k)
          and all(isinstance(p, Tensor) and tuple(p.shape) == tuple(psf_shape) and bool(torch.isfinite(p).all())
                  and bool((p >= 0).all()) for p in psfs.values()))
    if not ok:
        raise RngcamError("cannot resume: the checkpoint's PSF-edge stage is not as rngcam writes it; "
                          "use --overwrite to start again")


def _copy(report: dict) -> dict:
    return {**report, "refits": [dict(r) for r in report.get("refits", [])]}


def _nth(k: int) -> str:
    return ("first", "second", "third", "fourth")[k] if k < 4 else f"#{k + 1}"


def edge_line(report: dict) -> str:
    """One note on what the edge stage did."""
    key = f"the key rows' PSF scale x{report['key_rows_scale']:.4f}"
    refits = report.get("refits") or []
    if not refits:
        return f"PSF edge not fitted ({key}): {report.get('why', 'the first fit has not ended')}"
    parts = []
    for i, r in enumerate(refits, 1):
        energy = "/".join(f"{100 * e:.1f}" for e in r["edge_energy"])
        ended = f", ended at {r['rs']:.4f}" if "rs" in r else " (not run to its own stop)"
        parts.append(f"from the {_nth(r['from_fit'])} fit's video x{r['scale']:.4f} ({r['edge_pixels']} pixels, "
                     f"{energy} % of the energy; RS residual {r['from_rs']:.4f} -> {r['residual']:.4f} on it): "
                     f"the {_nth(i)} fit{ended}")
    why = f"; no more: {report['why']}" if report.get("why") else ""
    return (f"PSF edge ({key}): the PSF shrunk and its lost edge fitted " + "; ".join(parts)
            + f"; the {_nth(report['kept'])} fit kept{why}")
