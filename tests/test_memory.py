"""Memory: what a run keeps and when it refuses. Video-sized buffers a method can recompute or keep
in half precision are not held in float32 (the coarse-to-fine start, the start floor's video, the
power-iteration vector), a copy of a method's state shares the videos it never changes, and
--max-memory refuses before any frame or the truth is read."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

import rngcam
from rngcam.cli import main
from rngcam.errors import SettingError
from rngcam.formats.bundle import read_bundle
from rngcam.recon import registry, runner
from rngcam.recon.loop import LoopSettings, MethodBase, run
from rngcam.recon.methods.coarse_to_fine import Kept, upsample
from rngcam.recon.methods.stfm import STFMSettings, make_stfm
from rngcam.recon.methods.stfm.floor import MAKERS, StartFloor
from rngcam.recon.methods.stfm.multilevel import make_multilevel
from rngcam.recon.methods.tv3d import TV3D, TV3DSettings
from rngcam.sim.scenes import render_scene
from rngcam.sim.simulate import simulate, simulation_timing
from rngcam.video_plan import LIBRARY_BYTES, method_bytes, plan_grid


def _toy_problem(h=32, w=48):
    from rngcam.recon.problem import problem_from_video
    from rngcam.sim.simulate import prepare_simulation_psf

    timing = simulation_timing((h, w))
    video = torch.from_numpy(render_scene("smoke", timing.grid, (h, w), 0)).double()
    psf = prepare_simulation_psf(None, (h, w), (h, w), 0.25).grid
    return problem_from_video(video, torch.from_numpy(psf), timing.rs, timing.gs).to(torch.float32)


@pytest.fixture(scope="module")
def small_bundle(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("mem") / "s.h5"
    simulate("smoke", path, size=32)
    return path


def test_max_memory_refuses_before_the_frames_or_the_truth_are_read(small_bundle, monkeypatch):
    def never(*args, **kwargs):
        raise AssertionError("the problem was built before the size check refused")

    monkeypatch.setattr(runner, "build_problem", never)
    with pytest.raises(SettingError, match="max_memory_bytes") as err:
        rngcam.reconstruct(small_bundle, method="tv3d", max_memory_bytes=2**20, progress=False)
    assert "tv3d would need about" in str(err.value) and "\n" not in str(err.value)


def test_max_memory_on_the_command_line_is_one_line(small_bundle, tmp_path):
    res = CliRunner().invoke(main, ["recon", str(small_bundle), "--method", "blend", "--max-memory", "0.001",
                                    "-o", str(tmp_path / "o"), "--quiet"])
    assert res.exit_code != 0
    errors = [line for line in res.output.splitlines() if line.lower().startswith("error")]
    assert len(errors) == 1 and "--max-memory" in errors[0] and "blend would need about" in errors[0]
    assert not (tmp_path / "o").exists()


def test_the_prediction_is_within_15_percent_of_a_measured_run(small_bundle, tmp_path):
    """The child's own peak (VmHWM at its exit) against rngcam.video_plan's estimate, for a one-shot and
    an iterative method. Not the child's rusage: Linux counts the forking parent's peak (pytest's,
    over a GiB late in a full run) in a child's ru_maxrss. The libraries' resident file pages are
    taken as the model's nominal LIBRARY_BYTES: how many the kernel maps depends on the page cache
    (on a fresh CI venv the same run showed ~120 MiB more of them, its anonymous memory unchanged)."""
    plan = plan_grid(read_bundle(small_bundle))
    for method, extra in (("blend", []), ("tv3d", ["--iters", "3"])):
        args = ["recon", str(small_bundle), "--method", method, "-o", str(tmp_path / method), "--quiet", *extra]
        peak_file = tmp_path / f"{method}.peak"
        child = ("from rngcam.cli import main\nfrom rngcam.memory import mapped_file_bytes, peak_rss_bytes\n"
                 f"main({args!r}, standalone_mode=False)\n"
                 f"open({str(peak_file)!r}, 'w').write(f'{{peak_rss_bytes()}} {{mapped_file_bytes()}}')\n")
        subprocess.run([sys.executable, "-c", child], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
        peak, mapped = map(int, peak_file.read_text().split())
        assert 0 < mapped < peak
        measured = peak - mapped + LIBRARY_BYTES  # file pages only grow: peak - mapped <= the anonymous peak
        predicted = method_bytes(plan, registry.get(method).memory)
        assert abs(predicted - measured) <= 0.15 * measured, (method, predicted / 2**20, measured / 2**20,
                                                             mapped / 2**20)


def test_a_fine_stfm_level_keeps_its_start_once_in_half_precision(monkeypatch):
    from rngcam.recon.methods.stfm import multilevel

    monkeypatch.setattr(multilevel, "FINE_GS_MAX_PIXELS", 0)  # a large grid's: no GS-only detail added to it
    p = _toy_problem()
    m = make_multilevel(p, STFMSettings(rows_per_step=4, dynamic_base="video", refine=False), "cpu", (2, 1),
                        lambda q, s: make_stfm(q, s), max_level_steps=3)
    while not m.final:
        m.step()
    fine = m.method
    assert fine.base.video.dtype == torch.float16 and fine.base.video.shape == p.shape
    assert fine.base.video.data_ptr() == m._x0.data_ptr()  # the level's start and its base: one buffer
    assert fine.rs_norm_vector is None  # the full grid keeps no power-iteration vector
    state = copy.deepcopy(m.state_dict())  # what the loop keeps as its last good state
    assert state["x0"].tensor is m._x0  # shared, not copied
    m.step()
    assert torch.isfinite(m.estimate()).all()


def test_a_fine_level_divides_the_start_by_the_gains_on_the_fly(monkeypatch):
    from rngcam.recon.methods.stfm import multilevel

    monkeypatch.setattr(multilevel, "FINE_GS_MAX_PIXELS", 0)  # a large grid's: the start itself is the base
    p = _toy_problem()
    p.white_balance = torch.tensor([1.1, 1.0, 0.9])
    m = make_multilevel(p, STFMSettings(rows_per_step=4, dynamic_base="video", refine=False, init="random"),
                        "cpu", (2, 1), lambda q, s: make_stfm(q, s), max_level_steps=2)
    while not m.final:
        m.step()
    fine = m.method
    assert fine.base.video.data_ptr() == m._x0.data_ptr()
    idx = torch.arange(p.shape[1])
    xs, ys = fine.grid.xs.view(1, 1, -1).expand(len(idx), p.shape[2], -1), fine.grid.ys.view(1, -1, 1).expand(len(idx), -1,
                                                                                                      p.shape[3])
    base = fine.base.at(xs, ys, idx)
    expected = m._x0.float() / torch.tensor([1.1, 1.0, 0.9])[:, None, None, None]
    torch.testing.assert_close(base, expected, rtol=1e-5, atol=1e-6)


def test_the_start_floor_keeps_no_video_until_it_is_the_output():
    p = _toy_problem()
    fit = make_stfm(p, STFMSettings(rows_per_step=4, dynamic_base="video", refine=False))
    guard = StartFloor(fit, p)
    assert guard.start_name in MAKERS and guard._start_video is None
    real = guard._start_pred  # the reference's RS prediction: all the check keeps of it
    guard._start_pred = torch.full_like(real, 1e3)  # a reference far off: the output is the fit, no video made
    assert guard.estimate() is fit.estimate() and guard._start_video is None
    guard._start_pred, guard._checked = real, None  # the real one, which the unfitted fit does not beat here
    out = guard.estimate()
    assert guard.check["output"] == guard.start_name  # it is made again, exactly
    keys = guard._problem.gs_images(gains=True).numpy()
    torch.testing.assert_close(out, torch.from_numpy(MAKERS[guard.start_name](keys, p.gs_times_s, p.frame_times_s)))


def test_the_start_floor_lets_a_coarse_levels_reference_go_before_each_step():
    class Levels(MethodBase):  # a coarse-to-fine run at a coarse level, then at its final one
        name, stops_itself, final = "levels", True, False

        def __init__(self, video):
            self.video, self.steps = video, 0

        def step(self):
            self.steps += 1
            return 0.0

        def estimate(self):
            return self.video

    p = _toy_problem()
    inner = Levels(torch.zeros(p.shape))  # worse than every GS-only video: the output is the reference
    guard = StartFloor(inner, p)
    first = guard.estimate().clone()
    assert guard._start_video is not None and guard.check["output"] == guard.start_name
    guard.step()  # a coarse level's step may build the next level: the reference is not held through it
    assert inner.steps == 1 and guard._start_video is None
    torch.testing.assert_close(guard.estimate(), first)  # made again when asked for, the same video
    inner.final = True  # the final level keeps it between steps (it is the output)
    guard.step()
    assert inner.steps == 2 and guard._start_video is not None


def test_tv3d_state_copies_share_the_videos_and_a_rollback_still_works():
    p = _toy_problem(16, 24)
    m = TV3D(p, TV3DSettings())
    m.step()
    saved = copy.deepcopy(m.state_dict())
    assert isinstance(saved["x"], Kept) and saved["x"].tensor is m.state["x"]
    x_then = m.state["x"].clone()
    m.step()
    m.step()
    m.load_state_dict(copy.deepcopy(saved))
    torch.testing.assert_close(m.estimate(), x_then)  # nothing changed the kept tensors in place
    result = run(m, LoopSettings(time_budget_s=None, max_iters=4, progress=False, log_every_s=0.0))
    assert result.status == "ok"


def test_upsample_in_chunks_matches_the_whole_and_casts_to_the_storage_dtype():
    v = torch.rand(3, 7, 5, 6, generator=torch.Generator().manual_seed(0))
    whole = upsample(v, (3, 13, 10, 12), 2.0, frames=1000)
    torch.testing.assert_close(upsample(v, (3, 13, 10, 12), 2.0, frames=3), whole)
    half = upsample(v, (3, 13, 10, 12), 2.0, dtype=torch.float16)
    assert half.dtype == torch.float16
    torch.testing.assert_close(half.float(), whole, rtol=1e-3, atol=1e-3)


def test_rs_operators_share_their_scratch_and_keep_their_zero_padding_apart():
    from rngcam.physics import operators

    gen = torch.Generator().manual_seed(0)
    psf = torch.rand(3, 8, 8, generator=gen)
    big = operators.RollingShutter(psf, torch.rand(20, 6, generator=gen), width=20, channels=3)
    small = operators.RollingShutter(psf, torch.rand(19, 6, generator=gen), width=19, channels=3)
    assert big.conv.fft_shape == small.conv.fft_shape  # the same scratch shapes: one pool entry each
    v_big, v_small = torch.rand(3, 6, 20, 20, generator=gen), torch.rand(3, 6, 19, 19, generator=gen)
    big.A(v_big)
    got = small.A(v_small)  # after the larger image filled the shared buffer's padding region
    with torch.enable_grad():  # the same arithmetic without kept buffers
        fresh = small.A(v_small.clone().requires_grad_()).detach()
    torch.testing.assert_close(got, fresh)
    assert len([k for k in operators._scratch() if k[0] == "padded"]) <= operators.SCRATCH_PER_NAME


class _SavedBytes:
    """Autograd's saved tensors alive at once, in bytes (the peak over a step): what a graph holds."""

    def __init__(self):
        self.alive = self.peak = 0

    def pack(self, t):
        counter = self

        class Held:
            def __init__(self):
                self.t, self.n = t, t.numel() * t.element_size()
                counter.alive += self.n
                counter.peak = max(counter.peak, counter.alive)

            def __del__(self):
                counter.alive -= self.n

        return Held()

    @staticmethod
    def unpack(held):
        return held.t


def test_an_stfm_step_holds_one_chunk_of_frames_in_its_graph_at_a_time():
    p = _toy_problem(24, 32)
    peaks = {}
    for chunk in (64, 2):
        m = make_stfm(p, STFMSettings(rows_per_step=6, dynamic_base="video", refine=False, frame_chunk=chunk,
                                      gs_windows_per_step=1))
        saved = _SavedBytes()
        with torch.autograd.graph.saved_tensors_hooks(saved.pack, saved.unpack):
            m.loss.loss_terms(torch.arange(6, 12), torch.tensor([1, 5]), backward=True, gs_windows=torch.tensor([1]))
        peaks[chunk] = saved.peak
        assert saved.alive == 0  # every graph freed by the end of the step
    assert peaks[2] < 0.6 * peaks[64], peaks  # the chunks' graphs are not kept until the last one


def test_a_graph_saves_what_the_gpu_chunk_assumes_per_point():
    from rngcam.recon.methods.stfm.settings import GRAPH_BYTES_PER_POINT

    p = _toy_problem(48, 64)
    m = make_stfm(p, STFMSettings(dynamic_base="video", refine=False, frame_chunk=8))
    saved = _SavedBytes()
    with torch.autograd.graph.saved_tensors_hooks(saved.pack, saved.unpack):
        m.model.frames(torch.arange(8), m.model.static()).sum().backward()
    per_point = saved.peak / (8 * 48 * 64)
    assert 0.3 * GRAPH_BYTES_PER_POINT < per_point < 1.25 * GRAPH_BYTES_PER_POINT, per_point


@pytest.mark.parametrize("card_gib, frames", [(80, 32), (8, 11), (1, 4)])
def test_a_gpu_takes_larger_frame_chunks_bounded_by_its_memory(monkeypatch, card_gib, frames):
    from types import SimpleNamespace

    from rngcam.recon.methods.stfm.settings import chunk_frames

    monkeypatch.setattr(torch.cuda, "get_device_properties",
                        lambda _dev: SimpleNamespace(total_memory=int(card_gib * 2**30)))
    assert chunk_frames(STFMSettings(), 228, 342, "cuda") == frames  # the paper grid
    assert chunk_frames(STFMSettings(), 228, 342, "cpu") == 4
    assert chunk_frames(STFMSettings(frame_chunk=3), 228, 342, "cuda:0") == 3  # the setting wins
    assert chunk_frames(STFMSettings(), 64, 64, "cpu") == 32  # a step's RS frames in one graph at 64 px


def test_the_heap_is_trimmed_before_large_buffers_only(monkeypatch):
    """A trim before a small video (64 px) only made the next step fault its pages back in; before a
    buffer mapped afresh (at or over glibc's largest mmap threshold) it keeps the peak down."""
    import rngcam.memory as memory

    trims = []
    monkeypatch.setattr(memory, "release_free_memory", lambda collect=True: trims.append(collect))
    memory.release_before(67 * 64 * 64 * 3 * 4)
    assert trims == []
    memory.release_before(memory.LARGE_BUFFER_BYTES)
    memory.release_before(231 * 228 * 342 * 3 * 4)
    assert trims == [False, False]


# A step-like burst of large temporaries (48, 48 and 96 MiB, freed at its end), eight times: the
# minor page faults of the cheapest of the last four (the heap's free blocks take a few steps to
# settle into ones that fit), outside heap_reuse and inside it. In a fresh interpreter: what earlier
# tests left in this one's heap would decide what is reused.
_STEP_FAULTS = """
import json, resource, torch
import rngcam.memory as memory

def faults():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    x = torch.ones(12 * 2**20)
    float(torch.cat([x, x * 2])[-1])
    del x
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

with torch.inference_mode():
    outside = min([faults() for _ in range(8)][4:])
    with memory.heap_reuse():
        with memory.heap_reuse():  # nested: the outer's setting holds after the inner leaves
            pass
        inside = min([faults() for _ in range(8)][4:])
print(json.dumps([outside, inside]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc and getrusage's fault count")
def test_inside_heap_reuse_a_steps_large_temporaries_reuse_the_heap_without_page_faults():
    """glibc maps a buffer over 32 MiB afresh and unmaps it on free, so each one is faulted in page by
    page again (at 228x342 a step's temporaries: 0.3-0.4 M faults a step); inside heap_reuse the freed
    pages stay in the heap for the next step."""
    import json

    done = subprocess.run([sys.executable, "-c", _STEP_FAULTS], capture_output=True, text=True, check=True,
                          cwd=Path(rngcam.__file__).parents[1])
    outside, inside = json.loads(done.stdout.strip().splitlines()[-1])
    assert outside > 8_000  # 49,152 pages of 4 KiB
    assert inside < 1_000


def test_returned_on_free_hands_a_freed_buffer_back():
    """In a heap that keeps what is freed (no trimming on free; buffers under glibc's largest mmap
    threshold from the heap, as after a fit's steps), a buffer freed inside `returned_on_free` is out of
    the resident set when it ends; freed outside it, it stays."""
    import contextlib

    import numpy as np

    from rngcam import memory

    if memory._glibc() is None:
        pytest.skip("glibc's malloc_trim and mallopt only")
    size = 24 * 2**20

    def kept_after(context) -> float:
        with context():
            big = np.ones(size // 8)  # touched: resident
            held = memory.current_rss_bytes()
            del big
        return (memory.current_rss_bytes() - (held - size)) / 2**20

    memory._mallopt(memory._M_TRIM_THRESHOLD, 2**31 - 1)
    memory._mallopt(memory._M_MMAP_THRESHOLD, memory.LARGE_BUFFER_BYTES)
    try:
        memory.release_free_memory(collect=False)
        kept = kept_after(contextlib.nullcontext)
        memory.release_free_memory(collect=False)
        returned = kept_after(memory.returned_on_free)
    finally:
        memory._mallopt(memory._M_TRIM_THRESHOLD, memory._GLIBC_TRIM_THRESHOLD)
        memory.release_free_memory(collect=False)
    assert kept > 20 and returned < 4, (kept, returned)
