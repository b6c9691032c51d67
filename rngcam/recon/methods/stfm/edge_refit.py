"""Fits again through the PSF with its lost edge fitted, where a fit cannot explain the data.

Self-calibration's key rows find a PSF measured too large (rngcam.recon.methods.selfcal), but
shrunk on the grid it lacks the edge its measurement lost, and applied it never paid. Here the
first fit runs through the PSF as handed; where it stops clearly above its noise level and the
key rows found the PSF too large, its video fits that edge (rngcam.recon.methods.psf_edge), and
where the edge lowers the RS residual by `min_drop` another fit runs through that PSF; then
again from the best fit's video (a better video fits a better edge), at most `max_refits` times
(the psf_edge stage's config: stage_configs.EdgeRefitConfig).
The output is the fit that explains the RS image best (each through its own PSF; `refits`).
Figures: bench/realistic.md, "A PSF measured too large: its edge fitted".
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from rngcam.recon.methods.psf_edge import search_edge
from rngcam.recon.methods.stfm.refits import Refits, nth
from rngcam.recon.methods.stfm.stage_configs import EdgeRefitConfig, StopConfig

DROP_EPS = 1e-30  # the share the edge lowers the residual by stays finite where the residual is 0


def edge_scale(selfcal: dict | None, max_scale: float = EdgeRefitConfig.max_scale) -> float | None:
    """The key rows' PSF scale where it says the PSF was measured too large (not applied, <= `max_scale`),
    whether or not it lowered their residual: without its edge a shrunk PSF may not (smoke, PSF 5 % large)."""
    psf = ((selfcal or {}).get("scales") or {}).get("psf") or {}
    est = psf.get("estimate")
    if psf.get("applied") or not isinstance(est, float) or not 0 < est <= max_scale:
        return None
    return est


class EdgeRefit(Refits):
    """`first` (a whole STFM run) and, where the best fit so far ends unexplained, another through
    the PSF with its edge fitted to that fit's video: `refit(psf, edge_report)` makes such a run."""

    SETTING, RESULT, VALUE = "psf_edge", "edge_refits", "scale"
    STATE, STAGE_NAME = "edge", "PSF-edge"

    def __init__(self, first, problem, scale: float, refit: Callable, config: EdgeRefitConfig | None = None,
                 explained_ratio: float = StopConfig.explained_ratio):
        """An edge is fitted where the best fit's RS residual is `explained_ratio` x its noise level or more:
        the fit is not explained, where the key rows point at a PSF scale (rngcam.recon.misfit.POINTED_RATIO)."""
        super().__init__(first, problem, refit, {"key_rows_scale": scale}, explained_ratio=explained_ratio)
        self._config = config or EdgeRefitConfig()

    def _propose(self, best, res: float) -> tuple[Tensor, dict] | None:
        """Fit the edge to the best fit's video; the PSF for another fit where it pays."""
        noise = getattr(best, "rs_noise_level", None)
        n = len(self.report["refits"])
        if not noise or not res >= self.explained_ratio * noise:
            within = f"within {self.explained_ratio}x its noise level"
            self.report["why"] = f"the {nth(self._best)} fit's RS residual is {within}" if noise else "no noise level"
            return None
        if n >= self._config.max_refits:
            self.report["why"] = f"{self._config.max_refits} fits through a fitted edge made"
            return None
        if any(r["from_fit"] == self._best for r in self.report["refits"]):  # the same video, the same edge
            self.report["why"] = f"the fit through the edge the {nth(self._best)} fit's video gave did not do better"
            return None
        self.report["noise_level"] = noise
        with torch.no_grad():
            found = search_edge(self._problem, best.estimate())
        if found is None:
            self.report["why"] = ("no edge could be fitted (on a large grid the edge has more pixels than the RS "
                                  "rows a fit affords can pin: psf_edge.MAX_DESIGN)")
            return None
        drop = 1 - found["residual"] / max(res, DROP_EPS)
        attempt = {k: v for k, v in found.items() if k not in ("psf", "searched")}
        attempt.update(drop=drop, from_fit=self._best, from_rs=res)
        if not drop >= self._config.min_drop:
            self.report["why"] = (f"an edge fitted to the {nth(self._best)} fit's video (x{found['scale']:.4f}) lowers "
                                  f"its RS residual by {100 * drop:.1f} % (< {100 * self._config.min_drop:g} %)")
            self.report["not_refitted"] = attempt  # what the search found, reported though not fitted through
            return None
        return found["psf"], attempt

    def _check_made(self, made: dict) -> bool:
        """The fitted PSFs: the problem's shape, finite and non-negative."""
        shape = tuple(self._problem.psf.shape)
        return all(isinstance(p, Tensor) and tuple(p.shape) == shape and bool(torch.isfinite(p).all())
                   and bool((p >= 0).all()) for p in made.values())

    def _line(self, report: dict) -> str:
        return edge_line(report)


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
        parts.append(f"from the {nth(r['from_fit'])} fit's video x{r['scale']:.4f} ({r['edge_pixels']} pixels, "
                     f"{energy} % of the energy; RS residual {r['from_rs']:.4f} -> {r['residual']:.4f} on it): "
                     f"the {nth(i)} fit{ended}")
    why = f"; no more: {report['why']}" if report.get("why") else ""
    return (f"PSF edge ({key}): the PSF shrunk and its lost edge fitted " + "; ".join(parts)
            + f"; the {nth(report['kept'])} fit kept{why}")
