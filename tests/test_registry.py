"""The method registry: a new method is one class plus one registry entry, and it runs through
`reconstruct` and `rngcam recon` with options generated from its settings; every option of every
command is documented; one option name sets one field per method."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import click
import numpy as np
import pytest
import torch
from cli_tree import leaf_commands
from click.testing import CliRunner

from rngcam.cli import main
from rngcam.cli.method_options import method_settings
from rngcam.errors import ConfigError, SettingError
from rngcam.recon import registry
from rngcam.recon.loop import MethodBase
from rngcam.recon.methods.baselines import blend
from rngcam.recon.methods.stfm import STFMSettings
from rngcam.recon.methods.stfm.settings import PRESETS, preset_settings, resolve
from rngcam.recon.methods.tv3d import TV3DSettings
from rngcam.recon.options import setting
from rngcam.recon.runner import ReconSettings, reconstruct


@dataclass
class ToySettings:
    start: float = setting(0.5, "the value every voxel starts at", unit="linear intensity")
    pull: float = setting(0.5, "fraction of the way to the cross-fade each step", unit="fraction")


class Toy(MethodBase):
    """Moves a constant video a fixed fraction of the way to the key frames' cross-fade each step."""

    name = "toy"

    def __init__(self, problem, settings: ToySettings):
        key = problem.gs_images().float().numpy()
        self.target = torch.from_numpy(blend(key, problem.gs_times_s, problem.frame_times_s))
        self.pull = settings.pull
        self.video = torch.full_like(self.target, settings.start)

    def step(self) -> float:
        self.video = self.video + self.pull * (self.target - self.video)
        return float(torch.linalg.vector_norm(self.target - self.video))

    def estimate(self):
        return self.video

    def residuals(self) -> dict[str, float]:
        return {}

    def state_dict(self) -> dict:
        return {"video": self.video}

    def load_state_dict(self, state: dict) -> None:
        self.video = state["video"]

    def reduce_step(self, factor: float) -> None:
        self.pull *= factor


@pytest.fixture
def toy():
    entry = registry.register(registry.MethodEntry(
        "toy", registry.ITERATIVE, ToySettings, lambda problem, settings, **_: Toy(problem, settings)))
    yield entry
    registry.unregister("toy")


@pytest.fixture(scope="module")
def bundle(tmp_path_factory):
    from rngcam.sim.simulate import simulate

    path = tmp_path_factory.mktemp("toy") / "ball.h5"
    simulate("sineball", path, size=16, seed=0)
    return path


def _expected(bundle, start: float, pull: float, steps: int) -> np.ndarray:
    from rngcam.formats.bundle import read_bundle
    from rngcam.recon.problem import build_problem

    p = build_problem(read_bundle(bundle)).to(torch.float32)
    target = blend(p.gs_images().float().numpy(), p.gs_times_s, p.frame_times_s)
    return target + (start - target) * (1 - pull) ** steps


def test_a_toy_method_runs_through_reconstruct(toy, bundle, tmp_path):
    settings = ReconSettings(method="toy", method_settings=toy.settings(start=0.2), max_iters=3,
                             time_budget_s=None, progress=False)
    metrics = reconstruct(bundle, tmp_path / "out", settings, echo=lambda _: None)
    assert metrics["method"] == "toy" and metrics["iterations"] == 3
    assert metrics["method_settings"] == {"start": 0.2, "pull": 0.5}
    import h5py

    with h5py.File(tmp_path / "out" / "recon.h5") as f:
        video = f["video"][()]
    np.testing.assert_allclose(video, _expected(bundle, 0.2, 0.5, 3), rtol=1e-5, atol=1e-6)


def test_a_toy_method_runs_through_the_command_line_with_generated_options(toy, bundle, tmp_path):
    shown = CliRunner().invoke(main, ["recon", "--help"], terminal_width=200)
    assert shown.exit_code == 0
    assert "toy" in shown.output.split("--method")[1].splitlines()[0]
    line = next(ln for ln in shown.output.splitlines() if ln.strip().startswith("--pull"))
    assert "toy: fraction of the way to the cross-fade each step (fraction) [0.5]" in line
    out = tmp_path / "cli"
    res = CliRunner().invoke(main, ["recon", str(bundle), "--method", "toy", "--start", "0.1", "--pull", "0.25",
                                    "--iters", "2", "--quiet", "-o", str(out)])
    assert res.exit_code == 0, res.output
    assert json.loads((out / "metrics.json").read_text())["method_settings"] == {"start": 0.1, "pull": 0.25}
    import h5py

    with h5py.File(out / "recon.h5") as f:
        np.testing.assert_allclose(f["video"][()], _expected(bundle, 0.1, 0.25, 2), rtol=1e-5, atol=1e-6)
    wrong = CliRunner().invoke(main, ["recon", str(bundle), "--method", "tv3d", "--pull", "0.3", "-o",
                                      str(tmp_path / "w")])
    assert wrong.exit_code == 2 and "--pull does not apply to --method tv3d" in wrong.output


def test_every_option_of_every_command_has_help():
    seen = 0
    for name, cmd in leaf_commands(main):
        ctx = click.Context(cmd, info_name=name)
        for param in cmd.get_params(ctx):
            if isinstance(param, click.Option):
                assert (param.help or "").strip(), f"rngcam {name} {param.opts[0]} has no help"
                seen += 1
        opts = [o for p in cmd.get_params(ctx) for o in p.opts]
        assert len(opts) == len(set(opts)), f"rngcam {name} declares an option twice"
    assert seen > 50


def test_recon_help_gives_each_method_its_meaning_unit_and_default():
    text = CliRunner().invoke(main, ["recon", "--help"], terminal_width=400).output
    beta = next(ln for ln in text.splitlines() if ln.strip().startswith("--beta"))
    assert "tv3d: weight of the TV along time relative to along x and y (relative) [1]" in beta
    assert "stfm" not in beta  # stfm's beta is --set fit.beta=...
    swept = CliRunner().invoke(main, ["sweep", "--help"], terminal_width=400).output  # a sweep grids stfm's too
    beta = next(ln for ln in swept.splitlines() if ln.strip().startswith("--beta"))
    per_preset = ", ".join(f"{name} {preset_settings(name).beta:g}" for name in ("fast", "paper", "prior"))
    assert "stfm: weight of the motion field's change along time" in beta and f"[{per_preset}]" in beta
    fits = next(ln for ln in text.splitlines() if ln.strip().startswith("--fits"))
    assert "stfm: independent fits of one dynamic base" in fits and "(fits) [the preset's]" in fits
    for flag in ("--no-rs", "--no-gs", "--no-static", "--no-motion-reg", "--gs-anchor"):
        assert next(ln for ln in text.splitlines() if ln.strip().startswith(flag)).split(flag, 1)[1].strip()


def test_one_option_sets_one_field_per_method():
    tv3d, stfm = method_settings("tv3d", {"no_rs": True}), method_settings("stfm", {"no_rs": True})
    assert isinstance(tv3d, TV3DSettings) and tv3d.no_rs and isinstance(stfm, STFMSettings) and stfm.no_rs
    prior = method_settings("stfm", {"preset": "prior", "fits": 1})
    assert prior == dataclasses.replace(preset_settings("prior"), fits=1) and prior.preset == "prior"
    assert method_settings("tv3d", {"preset": "exact"}).prox == "exact"
    with pytest.raises(click.UsageError, match="--preset does not apply to --method pnp"):
        method_settings("pnp", {"preset": "fast"})


def test_labels_name_a_method_and_preset_in_one_spelling():
    assert registry.labels() == ("stfm-auto", "stfm-fast", "stfm-paper", "stfm-prior", "tv3d-haar", "tv3d-exact", "pnp",
                                 "blend", "interp", "rife")
    name, settings = registry.settings_for("stfm-prior", beta=3.0)
    assert name == "stfm" and settings == dataclasses.replace(preset_settings("prior"), beta=3.0)
    assert registry.settings_for("stfm") == ("stfm", preset_settings("auto"))
    for bad, why in (("stfm_fast", "method 'stfm_fast' is not one of"), ("stfm-slow", "method 'stfm-slow' is not")):
        with pytest.raises(SettingError, match=why) as err:
            registry.parse_label(bad)
        assert err.value.settings == ("method",)
    with pytest.raises(SettingError, match="tv3d has no setting mu") as err:
        registry.settings_for("tv3d", mu=1.0)
    assert err.value.settings == ("mu",)
    with pytest.raises(SettingError, match="beta must be a finite number") as err:  # the settings' own check
        registry.settings_for("stfm", beta=-1.0)
    assert err.value.settings == ("beta",) and err.value.flagged({"beta": "--beta"}).startswith("stfm: --beta must")
    with pytest.raises(ConfigError, match="takes TV3DSettings, not STFMSettings"):
        ReconSettings(method="tv3d", method_settings=STFMSettings())


@pytest.mark.parametrize("preset", [p for p in PRESETS if p != "auto"])  # auto picks one of them per scene
@pytest.mark.parametrize("shape", [(16, 16, 9), (64, 48, 67)])
def test_a_registry_preset_resolves_like_the_bare_preset_name(preset, shape):
    """The registry's STFM presets carry the preset's values; a fit from them is the fit of
    STFMSettings(preset=...), whose Nones the preset fills per problem."""
    filled, _ = resolve(preset_settings(preset), *shape)
    bare, _ = resolve(STFMSettings(preset=preset), *shape)
    assert preset_settings(preset).beta is not None and preset_settings(preset).rows_per_step is None
    assert preset_settings(preset).stall_passes is None  # the fast preset's depends on the grid
    assert {**dataclasses.asdict(filled), "settings": None} == {**dataclasses.asdict(bare), "settings": None}


@pytest.mark.parametrize("name", registry.names(registry.ITERATIVE))
def test_every_iterative_method_implements_the_whole_protocol(name):
    from tiny_scenes import tiny_sineball_problem

    entry = registry.get(name)
    problem = tiny_sineball_problem(16).to(torch.float32)
    method = entry.factory(problem, entry.settings(), device="cpu", clock=None, stage=None)
    assert isinstance(method, MethodBase) and method.name == name
    assert np.isfinite(method.step()) and tuple(method.estimate().shape) == tuple(problem.shape)
    assert isinstance(method.supports_holdout, bool) and isinstance(method.stops_itself, bool)
    assert method.supports_holdout == entry.fits_holdout  # the entry says what its methods do
    assert all(len(item) == 2 for item in method.left_out) and all(isinstance(n, str) for n in method.notes)
    assert method.converged() is None or isinstance(method.converged(), str)
    assert isinstance(method.budget_cut(), str) and isinstance(method.components(), dict)
    resolved = method.resolved_settings()
    assert resolved is None or isinstance(resolved, dict)


def test_rife_below_the_flow_size_is_the_cross_fade_and_says_so():
    """As interp: key frames too small for any flow (RIFE would pad 4 px to its 64 px working size and
    spend minutes guessing) give the cross-fade, with a note saying why."""
    from rngcam.recon.methods.baselines import blend

    rng = np.random.default_rng(0)
    keys = rng.random((3, 3, 4, 4)).astype(np.float32)
    gs_t, frame_t = np.array([0.0, 1.0, 2.0]), np.linspace(0, 2, 40)
    made = registry.get("rife").factory(keys, gs_t, frame_t, registry.get("rife").settings_type())
    np.testing.assert_allclose(made.video, blend(keys, gs_t, frame_t), rtol=1e-6, atol=1e-7)
    assert any("4x4 px" in n and "cross-fade" in n for n in made.notes)
