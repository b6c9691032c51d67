"""The self-check's held-out rows: the motion search reads them, the check judges on them, and a kept fit
then takes them in (the polish) and runs to its next stop."""

from dataclasses import replace

import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.recon.loop import MethodBase
from rngcam.recon.methods import rife as rife_method
from rngcam.recon.methods.stfm import STFMSettings
from rngcam.recon.methods.stfm.ensemble import STFMEnsemble
from rngcam.recon.methods.stfm.floor import StartFloor
from rngcam.recon.methods.stfm.method import STFM
from rngcam.recon.methods.stfm.recipe import make_stfm
from rngcam.recon.methods.stfm.run_state import RunState


def _noisy(problem, sigma: float, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    return replace(problem, b_rs=problem.b_rs + sigma * torch.randn(problem.b_rs.shape, generator=gen))


class _Stopping(MethodBase):
    """A fit that has stopped, and counts what the check asks of it."""

    name = "stopping"
    stops_itself = True

    def __init__(self, video):
        self.video, self.every_row, self.steps = video, 0, 7

    def estimate(self):
        return self.video

    def converged(self):
        return "stopped"

    def fit_every_row(self):
        self.every_row += 1
        return True

    def state_dict(self):
        return {"every_row": self.every_row}

    def load_state_dict(self, state):
        self.every_row = state["every_row"]


def _problem():
    return _noisy(tiny_sineball_problem(24).to(torch.float32), 0.002).with_holdout(0.2)


def test_a_kept_fit_takes_the_held_out_rows_in_and_runs_to_its_next_stop():
    p = _problem()
    fit = _Stopping(p.truth.clone())
    floor = StartFloor(fit, p)
    assert floor.converged() is None and fit.every_row == 1  # judged, kept, polishing
    assert floor.check["output"] == "fit" and floor.polish == {"after": "stopped", "at_step": 7}
    assert floor.converged() == "stopped; then, with the held-out RS rows fitted in: stopped" and fit.every_row == 1
    # The judgement stands as made before the polish: the polished video is the output, not judged again.
    fit.video = torch.zeros(p.shape)
    assert torch.equal(floor.estimate(), fit.video) and floor.check["output"] == "fit"
    assert floor.resolved_settings()["start_floor"]["polish"]["after"] == "stopped"
    # A resume carries the judgement made before the polish.
    again = StartFloor(_Stopping(p.truth.clone()), p)
    again.load_state_dict(floor.state_dict())
    assert again.polish == floor.polish and again.check == floor.check
    assert again.converged().startswith("stopped; then")


def test_a_fit_that_gives_way_is_not_polished():
    p = _problem()
    fit = _Stopping(torch.zeros(p.shape))
    floor = StartFloor(fit, p)
    assert floor.converged() == "stopped" and fit.every_row == 0 and floor.polish is None
    assert torch.equal(floor.estimate(), floor.start_video)


def test_without_a_split_or_with_polish_off_the_fit_ends_at_its_stop():
    p = _problem()
    for floor in (StartFloor(_Stopping(p.truth.clone()), p, polish=False),
                  StartFloor(_Stopping(p.truth.clone()), replace(p, rs_train_rows=None))):
        assert floor.converged() == "stopped" and floor._method.every_row == 0


def test_a_kept_fit_worse_on_the_held_out_rows_is_named(monkeypatch):
    """A fit right on every frame a fitted row sees and blank in the gap, against a video a little off
    everywhere: kept (better on the fitted rows), and a note says it is worse on the held-out rows."""
    p = _problem()
    seen = p.rs_weights[p.rs_train_rows].sum(0) > 0
    fit = p.truth.clone()
    fit[:, ~seen] = 0
    monkeypatch.setattr(rife_method, "rife", lambda *a, **k: (0.9 * p.truth).numpy())
    floor = StartFloor(_Stopping(fit), p, candidates=("rife",))
    floor.estimate()
    assert floor.check["output"] == "fit" and floor.guard_note is None
    assert floor.notes[-1].startswith("self-check: the fit explains the held-out RS rows worse than the GS-only "
                                      "video rife") and "kept" in floor.notes[-1]
    good = StartFloor(_Stopping(p.truth.clone()), p, candidates=("rife",))
    good.estimate()
    assert good.heldout_note is None and good.notes == []


def test_the_motion_search_reads_every_row_the_fit_only_the_fitted():
    p = _problem()
    settings = STFMSettings(preset="prior", fits=1, subframes=1, self_calibrate="off")
    own = RunState(rows_held_for_check=True)  # the hold_out stage's split
    split, whole = STFM(p, settings, state=own), STFM(replace(p, rs_train_rows=None), settings)
    assert torch.equal(split.motion_track_px, whole.motion_track_px)
    assert len(split.grid.rs_rows_fit) < p.shape[2] == len(whole.grid.rs_rows_fit)
    # A split handed to the run (a sweep's) stays out of the search too.
    handed = STFM(p, settings)
    assert not torch.equal(handed.motion_track_px, whole.motion_track_px)


def test_fit_every_row_puts_the_held_out_rows_into_the_steps_and_restarts_the_stop():
    p = _problem()
    fit = STFM(p, STFMSettings(preset="prior", fits=1, subframes=1, self_calibrate="off"))
    held = set(torch.nonzero(~p.rs_train_rows).flatten().tolist())
    assert not held & set(fit.loss.sample_rows().tolist())
    for _ in range(3):
        fit.step()
    fit.stop.history = {3: 0.5}
    assert fit.fit_every_row() and not fit.fit_every_row()
    assert fit.stop.history == {} and fit.stop.not_before == 3 + fit.stop.stall_window()
    drawn = set()
    for _ in range(200):
        drawn |= set(fit.loss.sample_rows().tolist())
    assert held <= drawn
    # A checkpoint remembers it.
    again = STFM(p, STFMSettings(preset="prior", fits=1, subframes=1, self_calibrate="off"))
    again.load_state_dict(fit.state_dict())
    assert len(again.grid.rs_rows_fit) == p.shape[2] and again.stop.not_before == fit.stop.not_before


def test_the_default_run_judges_then_polishes_every_fit_of_the_ensemble():
    """The recipe end to end, with a stop test quick enough for a test: the two fits stop, the check keeps
    their average, both fit every row to their next stop, and the run says so."""
    p = _noisy(tiny_sineball_problem(24).to(torch.float32), 0.002)  # the hold_out stage holds rows out
    settings = STFMSettings(preset="prior", start_floor=True, self_calibrate="off", subframes=1,
                            lr_half_life_steps=2.0, stall_passes=1, stall_drop=0.9)
    m = make_stfm(p, settings)
    floor = m
    while not isinstance(floor, StartFloor):
        floor = floor._method
    ensemble = floor._method
    assert isinstance(ensemble, STFMEnsemble) and len(ensemble.members) == 2
    done = None
    for _ in range(2000):
        m.step()
        done = m.converged()
        if done:
            break
    assert done and "then, with the held-out RS rows fitted in" in done, done
    assert floor.check["parts"]["held out"]["z"] is not None
    assert all(len(member.grid.rs_rows_fit) == p.shape[2] for member in ensemble.members)
    assert all(member.steps >= member.stop.not_before > 0 for member in ensemble.members)


def test_a_split_handed_to_the_run_stays_held_out():
    """A sweep scores the rows it held out: the check reads that split and no fit takes it in."""
    p = _noisy(tiny_sineball_problem(24).to(torch.float32), 0.002)
    settings = STFMSettings(preset="prior", start_floor=True, self_calibrate="off", subframes=1)
    own, handed = make_stfm(p, settings, trace=True), make_stfm(p.with_holdout(0.2), settings, trace=True)
    floors = []
    for m in (own, handed):
        while not isinstance(m, StartFloor):
            m = m._method
        floors.append(m)
    assert floors[0]._polish_on and not floors[1]._polish_on and floors[1].heldout
    assert any("a kept fit then fits every row" in line for line in own.recipe)
    assert not any("a kept fit then fits every row" in line for line in handed.recipe)

