"""STFM's stop test: the discrepancy principle and the stall test on the RS residual."""

from __future__ import annotations

import math

import torch

from rngcam.recon.methods.stfm.stage_configs import StopConfig
from rngcam.recon.metrics import relative_residual


class NoiseStop:
    """When a fit stops (`stop_at_noise`): the discrepancy principle and the stall test on its RS residual,
    whose recent values (`history`, step -> relative RS residual) it keeps."""

    def __init__(self, fit):
        self.fit = fit
        self.history: dict[int, float] = {}
        self.not_before = 0  # no test ends the fit before this step (a restart: `restart`)

    @torch.no_grad()
    def converged(self) -> str | None:
        """Every `check_every()` steps (`stop_at_noise`), the relative RS residual on
        the fitted rows is tested twice. The discrepancy principle: at or below the noise level
        estimated from the RS image (rngcam.recon.noise) the fit would start fitting noise. The
        stall test: once the residual fell by less than `stall_drop` over the last `stall_passes`
        passes over the rows, further steps buy little residual with structure the data do not
        demand (on the benchmark clips the truth-PSNR peaked there, then fell)."""
        fit = self.fit
        if not (fit.resolved.stop_at_noise and fit.parts.rs and fit.steps % self.check_every() == 0):
            return None
        fit.sync_line_time()
        grid = fit.grid
        rows = grid.rs_rows_fit.to(grid.device)
        video = fit.estimate()  # cached per step: a log at this step reuses it
        pred = fit.loss.rs_apply(lambda idx: video[:, idx], rows)
        target = fit.problem.b_rs.index_select(1, rows)
        if grid.rs_valid is not None:  # saturated pixels say nothing
            valid = grid.rs_valid.index_select(1, rows)
            pred, target = pred * valid, target * valid
        residual = relative_residual(pred, target)
        window = self.stall_window()
        steps, noise = fit.steps, fit.rs_noise_level
        self.history = {s: r for s, r in self.history.items() if s >= steps - window}
        self.history[steps] = residual  # only the last window is kept (and checkpointed)
        if steps < self._stop_from(window, residual):
            return None
        if residual <= noise:
            return (f"RS residual {residual:.4f} reached the noise level estimated from the RS image "
                    f"({noise:.4f}): more steps would fit noise")
        then = steps - window
        drop = fit.resolved.stall_drop
        if drop > 0 and then in self.history and residual > (1 - drop) * self.history[then]:
            passes = fit.resolved.stall_passes
            over = residual / noise if noise else float("inf")
            ratio = fit.fit_config.explained_ratio
            unexplained = f", more than the {ratio:g}x a fit that explains the data ends at" if over >= ratio else ""
            return (f"RS residual {residual:.4f} fell less than {100 * drop:g}% in {passes} passes over the "
                    f"rows (from {self.history[then]:.4f}; noise level {noise:.4f}: stopped at "
                    f"{over:.2f}x it{unexplained})")
        return None

    def restart(self) -> None:
        """Test afresh from this step, on the rows the fit now fits: its residual history goes, and neither
        test ends the fit within a stall window (what the window's passes fit is what the test measures)."""
        self.history = {}
        self.not_before = self.fit.steps + self.stall_window()

    def log_ready(self) -> bool:
        """A log row scores the video the stop test makes every `check_every()` steps: at those
        steps it is made once for both (a row elsewhere would make it again; bench/convergence.md,
        "the rows ride on the stop test")."""
        fit = self.fit
        return not (fit.resolved.stop_at_noise and fit.parts.rs) or fit.steps % self.check_every() == 0

    def check_every(self) -> int:
        """Steps between this fit's stop tests (`check_interval` of its frames)."""
        config = self.fit.fit_config
        return check_interval(self.fit.K, config.noise_check_steps, config.noise_check_frames)

    def _stop_from(self, window: int, residual: float) -> int:
        """The first step either test may stop the fit at this RS `residual`. Where the learned line time
        is held at first and the residual is at the noise level, its hold's end plus a stall `window`, so
        that it has been learned before the data are called explained (on half-frames a lab capture's fit
        reached its noise level with the line time still the recorded one: bench/realistic.md,
        "the prior preset fits half-frames"). A fit whose motion starts from the translation search
        (the prior preset) and whose residual is within `explained_ratio` of its noise level runs
        `search_fit_half_lives` (the fit stage's config) half-lives of its step first: its residual goes
        flat at the noise level long before its video settles (bench/realistic.md, "a search-started fit
        runs four half-lives of its step"). One that stalls unexplained stops as before, for the stages that
        fit again from it."""
        fit = self.fit
        line = fit.learned_line_time
        holds = [g.get("hold_steps", 0) for g in fit.optimiser.param_groups
                 if line.learned and g["params"][0] is line.parameter]
        hold = max(holds, default=0)
        start = hold + window if hold > 0 and residual <= fit.rs_noise_level else 0
        start = max(start, self.not_before)
        if residual < fit.fit_config.explained_ratio * fit.rs_noise_level:
            start = max(start, self.least_steps())
        return start

    def least_steps(self) -> int:
        """The steps this fit runs before its stop tests may end it while its data are explained:
        `search_fit_half_lives` (the fit stage's config) half-lives of its step for a fit whose motion
        starts from the translation search, else none (0)."""
        fit = self.fit
        half = fit.resolved.lr_half_life_steps
        lives = fit.fit_config.search_fit_half_lives
        return math.ceil(lives * half) if fit.search_started() and math.isfinite(half) else 0

    def stall_window(self) -> int:
        """`stall_passes` passes over the fitted rows, in steps (a multiple of `check_every()`)."""
        fit = self.fit
        steps = fit.resolved.stall_passes * len(fit.grid.rs_rows_fit) / fit.resolved.rows_per_step
        every = self.check_every()
        return every * max(1, math.ceil(steps / every))


def check_interval(frames: int, every: int = StopConfig.noise_check_steps,
                   per: int = StopConfig.noise_check_frames) -> int:
    """Steps between stop tests of a fit of `frames` frames: `every` up to `per` frames (the fit stage's
    config), one more interval for each further `per`. A test makes the whole video, a step
    only the frames of its rows, so at a fixed interval the tests' share of the time grows with the
    frames (bench/convergence.md, "the large grids' budget spent where it pays")."""
    return every * max(1, math.ceil(frames / per))
