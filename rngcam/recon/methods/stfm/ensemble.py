"""Several STFM fits on different dynamic bases (the fast preset's default), or of one base from
different seeds (the prior preset's two, `fits`), averaged and, with `refine`, refined."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from rngcam.recon.loop import MethodBase
from rngcam.recon.methods.stfm.grid import chunks
from rngcam.recon.methods.stfm.lanes import Lanes, lane_count
from rngcam.recon.methods.stfm.learned import geometry_report
from rngcam.recon.methods.stfm.line_time import line_time_report
from rngcam.recon.methods.stfm.method import STFM, add_learned, learned_notes
from rngcam.recon.methods.stfm.run_state import RunState
from rngcam.recon.methods.stfm.settings import STFMSettings, _setting_or_preset
from rngcam.recon.methods.stfm.stage_configs import fit_config

MAX_NOTE_CHARS = 300  # a note read back from a checkpoint is cut to one line's length


class STFMEnsemble(MethodBase):
    """Several STFM fits, one per dynamic base (or per entry of `bases`: a base listed again is fitted
    again from the next seed, initialised on its own), stepped in turn; the output is their average,
    refined by one more fit where `refine` is set.

    Each fit starts from a different GS-only guess (the RIFE video, or the key frames warped by
    RIFE's or DIS's flows) and the RS image corrects what it sees; what it cannot see (its null
    space) keeps each start's error, and those errors differ, so averaging shrinks them. The
    average stays consistent with the data: the operators are linear, so its residual is at most
    the members' mean residual. Steps go to the members with the fewest so far (members that have
    reached the noise level are done), as many side by side as the run has torch threads
    (rngcam.recon.methods.stfm.lanes): an iteration is one round, `member_steps` counts each fit's.

    Refinement (`refine`, fast preset): once every member has stopped, one more fit takes their
    average as its base video, with `fit.refine_lr_ratio` of the learning rate, until its own stop test
    fires (its stall test over `fit.refine_stall_passes` passes unless `stall_passes` is set); it is then the
    output. Like every fit it starts from the GS frames' static composition
    (alpha * static + (1 - alpha) * base, alpha where every key frame agrees with their median),
    which the members' fits had eroded; the RS image keeps that composition where it fits the data
    and undoes it where something moved between the key frames (bench/stfm_compare.md).
    Memory: one set of fields and one base per fit, and the output evaluated chunk by chunk into
    one buffer."""

    name = "stfm"
    stops_itself = True
    supports_holdout = True

    def __init__(self, problem, settings: STFMSettings, bases: list[str], device="cpu", first: STFM | None = None,
                 clock=None, state: RunState | None = None):
        self.settings = settings
        self._fit_config = fit_config(settings)  # the refinement's and the deadline check's numbers
        first_state = first.state if first is not None else (state or RunState())
        self.problem = problem
        self.members: list[STFM] = []
        self._of_one_base = len(set(bases)) < len(bases)  # fits of one base from several seeds (`fits`)
        sources = set()
        for i, base in enumerate(bases):
            again = bases[:i].count(base)  # a base listed again: another fit of it, initialised on its own
            if i == 0 and first is not None:
                member = first
            else:
                member = STFM(problem, replace(settings, dynamic_base=base, seed=settings.seed + i), device,
                              static_from=self.members[0] if self.members and not again else None,
                              state=self.members[0].state if self.members else first_state)
            if (member.base.source, again) in sources:  # e.g. "keys" falls back to DIS flows without RIFE
                continue
            sources.add((member.base.source, again))
            self.members.append(member)
        self.device = self.members[0].device
        self.steps = 0
        self._done: list[str | None] = [None] * len(self.members)
        self.use_refine = _setting_or_preset(settings, "refine")
        self.refined: STFM | None = None
        self._refine_done: str | None = None
        self._cache: tuple[int, Tensor] | None = None
        self._lanes = Lanes()
        self._clock = clock if self._of_one_base else None  # to let the later fits go where it cannot hold them
        self._timed: tuple[float, int] | None = None  # (perf_counter, member steps) at the first step
        self._let_go: str | None = None  # why the later fits were let go

    @property
    def state(self) -> RunState:
        """The fits' run state (one build's: rngcam.recon.methods.stfm.run_state)."""
        return self.members[0].state

    @property
    def left_out(self) -> list[tuple[str, str]]:
        return list(dict.fromkeys(item for m in self.members for item in m.left_out))

    @property
    def rs_noise_level(self) -> float | None:
        return self.members[0].rs_noise_level

    def _members_done(self) -> bool:
        return all(done is not None for done in self._done)

    def step(self) -> float:
        if self._members_done() and self.use_refine:
            if self.refined is None:
                self._start_refinement()
            value = self.refined.step()
            self._refine_done = self.refined.converged()
        else:
            active = sorted((j for j, done in enumerate(self._done) if done is None),
                            key=lambda j: self.members[j].steps) or [0]
            chosen = [self.members[j] for j in active[:lane_count(len(active))]]
            outcomes = self._lanes.run([member.fit_step for member in chosen])
            for j, (_, done) in zip(active, outcomes, strict=False):
                self._done[j] = done
            value = sum(v for v, _ in outcomes) / len(outcomes)
            self._afford()
            if self._members_done():
                self._lanes.close()
        self.steps += 1
        return value

    def _afford(self) -> None:
        """Fits of one base under a deadline: every `fit.afford_check_steps` of the first fit's steps, until it
        has run its least steps (`least_steps`), the steps all fits still need at the pace so far; where
        the time left does not hold them, the later fits are let go and the first runs on alone with their
        time: cut at half its steps each, two fits lose more than their average wins (bench/demo.md,
        "the prior preset's two fits"). Fits without least steps are not let go."""
        if len(self.members) < 2 or self._clock is None or self._clock.left() is None:
            return
        first = self.members[0]
        steps = sum(m.steps for m in self.members)
        if self._timed is None:
            self._timed = (time.perf_counter(), steps)
            return
        least = first.stop.least_steps()
        if first.steps % self._fit_config.afford_check_steps or first.steps >= least:
            return
        pace = (time.perf_counter() - self._timed[0]) / max(1, steps - self._timed[1])  # seconds a member step
        need = pace * sum(max(0.0, least - m.steps) for j, m in enumerate(self.members) if self._done[j] is None)
        left = self._clock.left()
        if need <= left:
            return
        self._let_go = (f"fits 2-{len(self.members)} let go at step {first.steps}: the {left:.0f} s left would cut "
                        f"every fit before its {least:,.0f} steps (at this pace {need:.0f} s); the output is the "
                        "first fit alone, not an average")
        self.members, self._done = self.members[:1], self._done[:1]
        self._cache = None
        self._lanes.close()

    def _start_refinement(self) -> None:
        first = self.members[0]
        config = self._fit_config
        lr = config.refine_lr_ratio * first.resolved.lr
        pose = self._mean_pose()
        video = self.estimate() if pose is None else self.average(native=True)  # the refinement's fields are native
        base = video / torch.as_tensor(self._mean_gains(), device=self.device)[:, None, None, None]
        settings = replace(self.settings, dynamic_base="video", seed=self.settings.seed + len(self.members), lr=lr,
                           stall_passes=self.settings.stall_passes or config.refine_stall_passes)
        self.refined = STFM(self.problem, settings, self.device, static_from=first, base_video=base, state=first.state)
        if pose is not None and self.refined.learned_pose.learned:  # the members' transform, refined further
            self.refined.start_pose(pose)
        factor = self._mean_line_factor()
        if factor is not None and self.refined.learned_line_time.learned:
            self.refined.start_line_factor(factor)

    def fit_every_row(self) -> bool:
        """The fit that makes the output (the refinement, else every member) fits the held-out RS rows too from
        here, until its stop test ends it again (stfm.floor); False where none had any held out."""
        if self.refined is not None:
            changed = self.refined.fit_every_row()
            self._refine_done = None if changed else self._refine_done
            return changed
        changed = [m.fit_every_row() for m in self.members]
        self._done = [None if c else d for c, d in zip(changed, self._done, strict=True)]
        self._cache = None
        return any(changed)

    def converged(self) -> str | None:
        if not self._members_done():
            return None
        done = (f"all {len(self.members)} ensemble members stopped" if not self._let_go else
                "the first fit stopped (the others were let go: see the notes)") + f"; first: {self._done[0]}"
        if not self.use_refine:
            return done
        if self._refine_done is None:
            return None
        return f"{done}; refinement: {self._refine_done}"

    @torch.no_grad()
    def average(self, native: bool = False) -> Tensor:
        """The members' average video (C, K, H, W) in RS coordinates (`native`: in the fields' own,
        the GS camera's, which the GS frames pin alike for every member)."""
        m0 = self.members[0]
        video = torch.zeros(m0.C, m0.K, m0.H, m0.W, device=self.device)
        for member in self.members:
            with member.averaged():
                for idx in chunks(torch.arange(m0.K, device=self.device), m0.frame_chunk):
                    video[:, idx] += member.model.video_frames(idx, native)
        return video.div_(len(self.members))  # in place: no second video-sized buffer

    @torch.no_grad()
    def estimate(self) -> Tensor:
        if self.refined is not None:
            return self.refined.estimate()
        if self._cache is None or self._cache[0] != self.steps:
            self._cache = None  # the stale video goes before the new one is made
            self._cache = (self.steps, self.average())
        return self._cache[1]

    def _mean_gains(self) -> np.ndarray:
        return np.mean([m.gains() for m in self.members], axis=0)

    def gains(self) -> np.ndarray:
        return self.refined.gains() if self.refined is not None else self._mean_gains()

    def _mean_pose(self) -> Tensor | None:
        poses = [m.pose() for m in self.members]
        return None if any(p is None for p in poses) else torch.stack(poses).mean(0)

    def pose(self) -> Tensor | None:
        """The learned GS-to-RS pose: the refinement's, else the members' mean (None: not learned)."""
        return self.refined.pose() if self.refined is not None else self._mean_pose()

    def _mean_line_factor(self) -> float | None:
        factors = [m.line_factor() for m in self.members]
        return None if any(f is None for f in factors) else float(np.mean(factors))

    def line_factor(self) -> float | None:
        """The learned line-time factor: the refinement's, else the members' mean (None: not learned)."""
        return self.refined.line_factor() if self.refined is not None else self._mean_line_factor()

    def line_time_report(self) -> dict | None:
        """The learned line time (line_time_report's), with each member's factor ("members"): how far the
        fits that saw the same rows from different starts agree on it."""
        first = self.members[0]
        start = first.state.line_time_from
        out = line_time_report(first.learned_line_time.timing, self.line_factor(), start)
        factors = [m.line_factor() for m in self.members]
        if out is not None and len(factors) > 1 and None not in factors:
            out["members"] = [start * f for f in factors]
        return out

    def learned_geometry(self) -> dict | None:
        m0 = self.members[0]
        return geometry_report(self.pose(), m0.learned_pose.radius, m0.state.selfcal_report)

    @torch.no_grad()
    def residuals(self) -> dict[str, float]:
        return (self.refined or self.members[0]).residuals_of(self.estimate(), self.gains(), self.line_factor())

    @torch.no_grad()
    def components(self) -> dict[str, np.ndarray]:
        """static and alpha of the refinement, else averaged over the members; motion of the
        first member (the refinement's motion moves the average, not the scene)."""
        out = self.members[0].components()
        if self.refined is not None:
            refined = self.refined.components()
            return {**out, "static": refined["static"], "alpha": refined["alpha"]}
        parts = [out, *(m.components() for m in self.members[1:])]
        return {**out, **{key: np.mean([p[key] for p in parts], axis=0) for key in ("static", "alpha")}}

    def state_dict(self) -> dict:
        return {"members": [m.state_dict() for m in self.members], "steps": self.steps, "done": list(self._done),
                "refined": None if self.refined is None else self.refined.state_dict(),
                "refine_done": self._refine_done, "let_go": self._let_go}

    def load_state_dict(self, state: dict) -> None:
        if state.get("let_go") and 1 == len(state["members"]) < len(self.members):  # the later fits let go
            self.members, self._done = self.members[:1], self._done[:1]
            self._let_go = str(state["let_go"])[:MAX_NOTE_CHARS]
        for m, saved in zip(self.members, state["members"], strict=True):
            m.load_state_dict(saved)
        self.steps = int(state["steps"])
        self._done = list(state["done"])
        self.refined = None
        if state.get("refined") is not None:  # rebuilt from the restored members, then restored
            self._start_refinement()
            self.refined.load_state_dict(state["refined"])
        self._refine_done = state.get("refine_done")
        self._cache = None

    def reduce_step(self, factor: float) -> None:
        for m in [*self.members, *([self.refined] if self.refined is not None else [])]:
            m.reduce_step(factor)

    def end_fit(self) -> None:
        self._cache = None
        for m in [*self.members, *([self.refined] if self.refined is not None else [])]:
            m.end_fit()

    def budget_cut(self) -> str:
        """Said when a time budget ends the run: which fits had not stopped by themselves."""
        open_members = [i + 1 for i, d in enumerate(self._done) if d is None]
        if open_members and self._let_go:
            return f"the first fit had not converged, the others were let go ({self.members[0].budget_cut()})"
        if open_members:
            return (f"ensemble members {', '.join(map(str, open_members))} of {len(self.members)} had not converged"
                    + (" and the refinement had not started" if self.use_refine else "")
                    + f" ({self.members[open_members[0] - 1].budget_cut()})")
        if self.use_refine and self._refine_done is None:
            return "the refinement fit had not converged" + (
                f" ({self.refined.budget_cut()})" if self.refined is not None else "")
        return ""

    def resolved_settings(self) -> dict:
        out = self.members[0].resolved_settings()
        out["dynamic_base"] = ",".join(m.resolved.dynamic_base for m in self.members)
        out["base_video"] = [m.base.source for m in self.members]
        out["member_steps"] = [m.steps for m in self.members]
        out["refine"] = self.use_refine
        out["refine_steps"] = None if self.refined is None else self.refined.steps
        return add_learned(out, self)

    @property
    def notes(self) -> list[str]:
        seeds = [m.settings.seed for m in self.members]
        fits = ([f"{len(seeds)} fits from seeds {', '.join(map(str, seeds))}, their videos averaged"]
                if self._of_one_base and len(seeds) > 1 else [])
        return self.members[0].notes_at_build + fits + ([self._let_go] if self._let_go else []) + learned_notes(self)
