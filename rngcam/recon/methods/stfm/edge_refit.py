"""A second fit through the PSF with its lost edge fitted, where a first fit cannot explain the data.

Self-calibration's key rows find a PSF measured too large (rngcam.recon.methods.selfcal), but
shrunk on the grid it lacks the edge its measurement lost, and applied it never paid. Here the
first fit runs through the PSF as handed; where it stops clearly above its noise level and the
key rows found the PSF too large, its video fits that edge (rngcam.recon.methods.psf_edge), and
where the edge lowers the RS residual by EDGE_MIN_DROP a second fit runs through that PSF. The
output is whichever fit explains the RS image better (each through its own PSF). Sineball with its
PSF 5 % large: 26.71 -> 35.29 dB, ball 1.29 / 11.93 -> 0.76 / 1.34 px (bench/realistic.md).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from rngcam.recon.loop import MethodBase

# The first fit's RS residual / its noise level at or above which the edge is tried: where the key
# rows point at a PSF scale (rngcam.recon.misfit.POINTED_RATIO)
EDGE_RATIO = 1.15
EDGE_MAX_SCALE = 0.99  # the key rows' PSF scale at or below which the PSF is taken as measured too large
EDGE_MIN_DROP = 0.15  # the share by which the fitted edge must lower the first video's RS residual


def edge_scale(selfcal: dict | None) -> float | None:
    """The key rows' PSF scale where it says the PSF was measured too large (not applied, <= EDGE_MAX_SCALE),
    whether or not it lowered their residual: without its edge a shrunk PSF may not (smoke, PSF 5 % large)."""
    psf = ((selfcal or {}).get("scales") or {}).get("psf") or {}
    est = psf.get("estimate")
    if psf.get("applied") or not isinstance(est, float) or not 0 < est <= EDGE_MAX_SCALE:
        return None
    return est


class EdgeRefit(MethodBase):
    """`first` (a whole STFM run) and, where it ends unexplained, a second one through the PSF with
    its edge fitted: `refit(psf, edge_report)` makes that run."""

    def __init__(self, first, problem, scale: float, refit: Callable):
        self._first, self._problem, self._scale, self._make_refit = first, problem, scale, refit
        self._method = first
        self._second = None
        self.report: dict = {"key_rows_scale": scale, "tried": False}
        self._first_rs: float | None = None

    def __getattr__(self, name):  # everything else is the current fit's
        if name.startswith("__") or name == "_method":
            raise AttributeError(name)
        return getattr(self._method, name)

    @property
    def supports_holdout(self) -> bool:
        return self._first.supports_holdout

    @property
    def stops_itself(self) -> bool:
        return self._first.stops_itself

    @property
    def left_out(self) -> list:
        return self._method.left_out

    def step(self) -> float:
        return self._method.step()

    def converged(self) -> str | None:
        why = self._method.converged()
        if why is None or self._second is not None or self.report["tried"]:
            if why is not None and self._second is not None:
                self._choose()
            return why
        self.report["tried"] = True
        if self._start_second():
            return None
        return why

    def budget_cut(self) -> str:
        return self._method.budget_cut()

    def reduce_step(self, factor: float) -> None:
        self._method.reduce_step(factor)

    def components(self) -> dict:
        return self._method.components()

    def _start_second(self) -> bool:
        """Fit the edge to the first fit's video; start the second fit where it pays."""
        from rngcam.recon.methods.psf_edge import search_edge

        res = self._first.residuals().get("rs")
        noise = getattr(self._first, "rs_noise_level", None)
        self._first_rs = res
        if res is None or not noise or res < EDGE_RATIO * noise:
            self.report["why"] = (f"the first fit's RS residual is within {EDGE_RATIO}x its noise level"
                                  if res is not None and noise else "no RS residual or noise level")
            return False
        with torch.no_grad():
            found = search_edge(self._problem, self._first.estimate())
        if found is None:
            self.report["why"] = "no edge could be fitted"
            return False
        drop = 1 - found["residual"] / max(res, 1e-30)
        self.report.update({k: v for k, v in found.items() if k != "psf"}, drop=drop, first_rs=res, noise_level=noise)
        if not drop >= EDGE_MIN_DROP:
            self.report["why"] = (f"the fitted edge lowers the RS residual by {100 * drop:.1f} % "
                                  f"(< {100 * EDGE_MIN_DROP:g} %)")
            return False
        self._second = self._make_refit(found["psf"], self.report)
        self._method = self._second
        self.report["refit"] = True
        return True

    def _choose(self) -> None:
        """The output: the second fit unless its RS residual (through its PSF) is not below the first's."""
        res = self._second.residuals().get("rs")
        self.report["second_rs"] = res
        keep = res is not None and self._first_rs is not None and res < self._first_rs
        self.report["kept"] = "second" if keep else "first"
        self._method = self._second if keep else self._first

    def estimate(self) -> Tensor:
        return self._method.estimate()

    def residuals(self) -> dict[str, float]:
        return self._method.residuals()

    def state_dict(self) -> dict:
        state = {"edge_stage": "second" if self._method is self._second else "first",
                 "first": self._first.state_dict()}
        if self._second is not None:
            state["second"] = self._second.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self._first.load_state_dict(state["first"])
        if state.get("second") is not None and self._second is not None:
            self._second.load_state_dict(state["second"])
        self._method = self._second if state.get("edge_stage") == "second" and self._second is not None else self._first

    @property
    def notes(self) -> list[str]:
        return list(self._method.notes) + ([edge_line(self.report)] if self.report["tried"] else [])

    def resolved_settings(self) -> dict | None:
        out = self._method.resolved_settings()
        out = {} if out is None else dict(out)
        out["psf_edge"] = dict(self.report)
        if isinstance(out.get("self_calibration"), dict):  # the misfit verdict reads it there
            out["self_calibration"] = dict(out["self_calibration"], psf_edge=dict(self.report))
        return out


def edge_line(report: dict) -> str:
    """One note on what the edge stage did."""
    key = f"the key rows' PSF scale x{report['key_rows_scale']:.4f}"
    if not report.get("refit"):
        return f"PSF edge not fitted ({key}): {report.get('why', 'the first fit has not ended')}"
    energy = "/".join(f"{100 * e:.1f}" for e in report["edge_energy"])
    line = (f"PSF edge: the PSF shrunk x{report['scale']:.4f} ({key}), its lost edge ({report['edge_pixels']} "
            f"pixels, {energy} % of the energy) fitted to the first fit's video: RS residual {report['first_rs']:.4f} "
            f"-> {report['residual']:.4f} on it")
    if report.get("kept") is None:
        return line + "; fitting again through it"
    return line + (f"; fitted again: {report['first_rs']:.4f} -> {report['second_rs']:.4f}, "
                   f"the {report['kept']} fit kept")
