"""The shared solver loop (with 3-D TV as its method): checkpoints, rollbacks, budgets and how a run ends."""

import itertools
import time

import pytest
import torch
from tiny_scenes import tiny_sineball_problem

from rngcam.recon import loop as loop_module
from rngcam.recon.loop import LoopSettings, run
from rngcam.recon.methods.tv3d import TV3D, TV3DSettings


def _sineball_problem(size=12):
    return tiny_sineball_problem(size, psf_seed=1)


def _settings(**kw):
    return LoopSettings(**{"time_budget_s": None, "progress": False, **kw})



def test_checkpoint_then_resume_equals_uninterrupted(tmp_path):
    p = _sineball_problem()
    straight = TV3D(p, TV3DSettings())
    run(straight, _settings(max_iters=12))
    first = TV3D(p, TV3DSettings())
    run(first, _settings(max_iters=5, checkpoint_dir=tmp_path))
    resumed = TV3D(p, TV3DSettings())
    result = run(resumed, _settings(max_iters=12, checkpoint_dir=tmp_path, resume=True))
    assert result.iterations == 12
    assert any("resumed" in e for e in result.events)
    torch.testing.assert_close(resumed.estimate(), straight.estimate(), rtol=0, atol=0)


class _Poisoned(TV3D):
    """Returns NaN on chosen iterations, as a diverging step would."""

    def __init__(self, problem, bad_calls):
        super().__init__(problem, TV3DSettings())
        self.calls, self.bad_calls, self.reductions = 0, set(bad_calls), 0

    def step(self):
        self.calls += 1
        f = super().step()
        if self.calls in self.bad_calls:
            self.state["x"] = self.state["x"] * float("nan")
            return float("nan")
        return f

    def reduce_step(self, factor):
        self.reductions += 1
        super().reduce_step(factor)


def test_injected_nan_is_rolled_back_and_recorded():
    m = _Poisoned(_sineball_problem(), bad_calls={3})
    result = run(m, _settings(max_iters=8, log_every_iters=1))
    assert result.status == "ok" and result.iterations == 8
    assert m.reductions == 1 and any("non-finite" in e for e in result.events)
    assert torch.isfinite(m.estimate()).all()


def test_an_overflowing_step_reaches_the_nan_guard():
    m = TV3D(_sineball_problem().to(torch.float32), TV3DSettings(restart=False))
    m.state["L"] *= 1e-30  # an absurd step: the objective overflows float32
    result = run(m, _settings(max_iters=3, log_every_iters=1, max_failures=2))
    assert result.status == "failed" and torch.isfinite(m.estimate()).all()
    assert any("non-finite" in e for e in result.events)


def test_backtracking_recovers_from_a_far_too_long_step():
    m = TV3D(_sineball_problem(), TV3DSettings(restart=True))
    sane_L, start = m.state["L"], m.state["F"]
    m.state["L"] *= 1e-12
    values = [m.step() for _ in range(5)]
    assert values[-1] < start and all(b <= a for a, b in itertools.pairwise(values))
    assert m.state["L"] >= sane_L / 2


def test_repeated_nan_stops_with_clear_message_and_last_good_state():
    m = _Poisoned(_sineball_problem(), bad_calls=set(range(4, 100)))
    result = run(m, _settings(max_iters=50, log_every_iters=1, max_failures=3))
    assert result.status == "failed" and "non-finite" in result.message and result.ended_by == "failure"
    assert torch.isfinite(m.estimate()).all() and result.iterations == 3


def test_time_budget_stops_the_loop():
    m = TV3D(_sineball_problem(), TV3DSettings())
    result = run(m, LoopSettings(time_budget_s=0.5, progress=False))
    assert 0.5 <= result.wall_s < 5 and result.iterations >= 1


def test_loop_needs_a_stopping_rule():
    with pytest.raises(ValueError):
        LoopSettings(time_budget_s=None, max_iters=None)
    from rngcam.recon.loop import Clock

    with pytest.raises(ValueError):
        LoopSettings(clock=Clock())  # a clock without a deadline and no iteration count


def test_the_loop_reads_the_runs_clock_and_says_once_how_it_ended():
    """The loop stops at the deadline of the clock it is given (the run's, started before it: set-up
    counts), and `ended_by` says what ended it: the budget, the iteration count, or both reached."""
    from rngcam.recon.loop import Clock

    clock = Clock(seconds=0.6)
    m = TV3D(_sineball_problem(), TV3DSettings())
    spent = clock.elapsed()  # the method's set-up, on the same clock
    result = run(m, LoopSettings(clock=clock, progress=False), setup_s=spent)
    assert result.ended_by == "budget" and result.status == "ok" and result.iterations >= 1
    assert 0.6 <= result.wall_s < 5 and clock.expired() and clock.left() <= 0
    assert any("time budget of 0.6 s reached" in e for e in result.events)
    by_count = run(TV3D(_sineball_problem(), TV3DSettings()), LoopSettings(clock=Clock(seconds=60), max_iters=2,
                                                                           progress=False))
    assert by_count.ended_by == "iterations" and by_count.iterations == 2
    late = Clock(start=0.0, seconds=1e-3)  # already past its deadline: nothing iterates
    cut = run(TV3D(_sineball_problem(), TV3DSettings()), LoopSettings(clock=late, progress=False))
    assert cut.ended_by == "budget" and cut.status == "budget_before_first_iteration" and cut.iterations == 0


class _Counting(TV3D):
    """TV3D that counts its steps."""

    def __init__(self, problem):
        super().__init__(problem, TV3DSettings())
        self.steps = 0

    def step(self):
        self.steps += 1
        return super().step()


class _StopsAt(_Counting):
    """TV3D that declares itself converged after a given number of steps."""

    stops_itself = True

    def __init__(self, problem, stop_after):
        super().__init__(problem)
        self.stop_after = stop_after

    def converged(self):
        return "enough" if self.steps >= self.stop_after else None


def test_a_converged_method_ends_the_run_early_with_its_reason():
    m = _StopsAt(_sineball_problem(), stop_after=4)
    result = run(m, _settings(max_iters=50, log_every_iters=10))
    assert result.status == "ok" and result.iterations == 4 and result.ended_by == "own_stop"
    assert result.log[-1]["iteration"] == 4  # the final state is logged
    assert any("stopped at iteration 4: enough" in e for e in result.events)
    assert not any("time budget" in e for e in result.events)


def test_a_budget_that_ends_a_run_before_the_methods_own_stop_says_so():
    cut = run(_StopsAt(_sineball_problem(), stop_after=10 ** 9), LoopSettings(time_budget_s=0.3, progress=False))
    assert any(e.startswith("time budget of 0.3 s reached at iteration") and "own stop" in e for e in cut.events)
    assert cut.status == "ok" and cut.ended_by == "budget"  # ok, but what ended it is on record
    # an iteration cap is the user's explicit choice: no budget event
    capped = run(_StopsAt(_sineball_problem(), stop_after=10 ** 9), _settings(max_iters=3))
    assert not any("time budget" in e for e in capped.events) and capped.ended_by == "iterations"
    # a method without a stop of its own (tv3d) is also cut by the budget, and says so
    plain = run(TV3D(_sineball_problem(), TV3DSettings()), LoopSettings(time_budget_s=0.3, progress=False))
    assert any("time budget of 0.3 s" in e and "no stop of its own" in e for e in plain.events)
    assert plain.ended_by == "budget"


def test_set_up_longer_than_the_budget_runs_no_step_and_says_so():
    result = run(TV3D(_sineball_problem(), TV3DSettings()), LoopSettings(time_budget_s=0.3, progress=False),
                 setup_s=0.5)
    assert result.iterations == 0 and len(result.log) == 1
    assert result.status == "budget_before_first_iteration" and result.ended_by == "budget"
    assert any("set-up alone took 0.5 s" in e for e in result.events)


def test_without_a_terminal_progress_goes_to_stderr_as_lines(capsys):
    run(TV3D(_sineball_problem(), TV3DSettings()),
        LoopSettings(time_budget_s=None, max_iters=6, log_every_iters=2, progress_every_s=0.0))
    err = capsys.readouterr().err
    assert err.count("tv3d: ") >= 3 and "iteration 6  RS residual 0.0" in err and "GS residual" in err


class _SlowToKeep(TV3D):
    """Cheap steps, a state that takes a while to snapshot (as an ensemble's does)."""

    def step(self):
        time.sleep(0.005)
        return super().step()

    def state_dict(self):
        time.sleep(0.03)
        return super().state_dict()


def test_log_spacing_counts_the_cost_of_keeping_the_state():
    """Logs are spaced by their whole cost (evaluation, the state's check and copy), not by the
    evaluation alone: 60 steps of 5 ms with a 30 ms snapshot give a handful of rows, not 60."""
    result = run(_SlowToKeep(_sineball_problem(), TV3DSettings()),
                 LoopSettings(time_budget_s=None, max_iters=60, log_every_s=1e-6, progress=False))
    assert result.iterations == 60 and 2 <= len(result.log) <= 15, len(result.log)


class _ReadyEvery(_Counting):
    """A method whose rows cost least every `n`-th step (as STFM's after its stop test)."""

    def __init__(self, problem, n):
        super().__init__(problem)
        self.n = n

    def log_ready(self):
        return self.steps % self.n == 0


def test_a_row_due_by_time_waits_for_the_method_to_be_ready(monkeypatch):
    # rows are also spaced by their own cost, which a loaded machine stretches (it skipped ready steps
    # here under load 3): held at zero, a row is due at every step by time alone
    monkeypatch.setattr(loop_module, "LOG_COST_RATIO", 0)
    result = run(_ReadyEvery(_sineball_problem(), 4),
                 LoopSettings(time_budget_s=None, max_iters=21, log_every_s=1e-6, progress=False))
    iterations = [row["iteration"] for row in result.log]
    # the start and the end are always kept; between them, a row where the method is ready and only there
    assert iterations == [0, 4, 8, 12, 16, 20, 21], iterations
    # rows asked for by count (log_every_iters) do not wait
    counted = run(_ReadyEvery(_sineball_problem(), 4), _settings(max_iters=6, log_every_iters=1))
    assert [row["iteration"] for row in counted.log] == list(range(7))
