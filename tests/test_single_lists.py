"""One list of each kind: the method registry (rngcam.recon.registry) is the only list of
reconstruction methods, rngcam.backends the only table of camera backends and generator
transports, and the generator dialects are one set (the driver's classes, the instrument
definitions and the rig file's type agree). docs/design.md, "Extension points", says what a new
method, backend or dialect touches."""

from __future__ import annotations

import ast
import dataclasses
import re
import typing
from pathlib import Path

import click
import pytest
import yaml
from cli_tree import leaf_commands

from rngcam.recon import registry

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "rngcam"

# Literals in rngcam/ that name two or more methods and are not a list of methods, each with
# why. Keyed by (file, the methods named): a list that changes is looked at again.
ALLOWED = {
    ("rngcam/recon/methods/pnp.py", ("blend", "interp", "rife")):
        "pnp's `init` values: the GS-only functions its start calls directly, plus `video`",
    ("rngcam/recon/methods/stfm/floor.py", ("blend", "interp", "rife")):
        "the self-check's candidate videos, made by calling the baselines' and RIFE's functions directly",
    ("rngcam/recon/methods/stfm/stage_configs.py", ("blend", "interp", "rife")):
        "the self-check's candidates as a stage setting: the videos floor.py can make",
    ("rngcam/recon/methods/stfm/settings.py", ("interp", "rife")):
        "STFM's base videos (`dynamic_base` values), not method names",
    ("rngcam/evaluate/stress_cases.py", ("stfm", "tv3d")):
        "the stress matrix's chosen fitted labels (a subset, for its run time); "
        "test_the_chosen_lineups_name_registered_labels holds them to the registry",
    ("rngcam/cli/demo.py", ("blend", "interp", "pnp", "rife", "stfm", "tv3d")):
        "the demo's plan: the preset and time budget of each part, chosen for the demo's scene and "
        "its 180 s; test_the_chosen_lineups_name_registered_labels holds them to the registry",
}


def _method_of(text: str) -> str | None:
    """The registered method a string names (a name or a NAME-PRESET label), else None."""
    name, _, preset = text.partition("-")
    entry = registry.REGISTRY.get(name)
    if entry is None or (preset and preset not in entry.presets):
        return None
    return name


def method_lists(source: str) -> list[tuple[int, tuple[str, ...]]]:
    """(line, methods named) of each outermost list, tuple, set or dict literal in `source` whose
    strings, nested ones included, name two or more registered methods."""
    found, inner = [], set()
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.List, ast.Tuple, ast.Set, ast.Dict)) or id(node) in inner:
            continue
        names = set()
        for sub in ast.walk(node):
            if sub is not node and isinstance(sub, (ast.List, ast.Tuple, ast.Set, ast.Dict)):
                inner.add(id(sub))
            if isinstance(sub, ast.Constant) and isinstance(sub.value, str):
                method = _method_of(sub.value)
                if method:
                    names.add(method)
        if len(names) >= 2:
            found.append((node.lineno, tuple(sorted(names))))
    return found


def _scan() -> dict[tuple[str, tuple[str, ...]], list[int]]:
    out: dict[tuple[str, tuple[str, ...]], list[int]] = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(REPO).as_posix()
        if rel == "rngcam/recon/registry.py":
            continue
        for line, names in method_lists(path.read_text()):
            out.setdefault((rel, names), []).append(line)
    return out


def test_the_scan_finds_a_list_of_methods_written_out():
    assert method_lists('CHOICES = ("stfm", "tv3d-exact")\n') == [(1, ("stfm", "tv3d"))]
    lineup = 'RUNS = [\n    ("blend", {}, None),\n    ("pnp", {"x": ("rife",)}, 40.0),\n]\n'
    assert method_lists(lineup) == [(1, ("blend", "pnp", "rife"))]
    assert method_lists('x = {"stfm": 1, "pnp": 2}\n') == [(1, ("pnp", "stfm"))]
    # one method, a preset that is not registered, and other strings are not a list of methods
    assert method_lists('a = ("stfm", "fast")\nb = ("tv3d-nope", "blend")\nc = ["video", "keys"]\n') == []


def test_no_module_keeps_its_own_list_of_methods():
    found = _scan()
    unexplained = {k: v for k, v in found.items() if k not in ALLOWED}
    assert not unexplained, ("a list of methods outside rngcam.recon.registry (take it from the registry, or "
                             f"add it to ALLOWED with the reason it is not one): {unexplained}")
    stale = sorted(set(ALLOWED) - set(found))
    assert not stale, f"ALLOWED names literals that are gone: {stale}"


def test_the_chosen_lineups_name_registered_labels():
    from rngcam.cli import demo
    from rngcam.evaluate import stress_cases

    assert set(stress_cases.ITERATIVE) <= set(registry.labels(registry.ITERATIVE))
    assert set(stress_cases.GS_ONLY) == set(registry.labels(registry.GS_ONLY))
    for label, *_ in demo.PLAN:
        registry.parse_label(label)  # a SettingError names a label the registry does not have


@pytest.fixture
def toy():
    toy_settings = dataclasses.make_dataclass("ToySettings", [])
    entry = registry.register(registry.MethodEntry("toy", registry.ITERATIVE, toy_settings, lambda *a, **k: None))
    yield entry
    registry.unregister("toy")


def test_every_method_option_of_the_command_line_is_the_registry(toy):
    """A method registered now is a --method choice of every command that takes one, with the
    registry's names in the registry's order (`rngcam bench`, whose choices are labels, is
    checked against the labels it had when it was imported)."""
    from rngcam.cli import main
    from rngcam.cli.method_options import MethodCommand

    seen = []
    for name, cmd in leaf_commands(main):
        ctx = click.Context(cmd)
        for param in cmd.get_params(ctx):
            choices = getattr(param.type, "choices", None)
            if not choices or not {_method_of(c) for c in choices} - {None}:
                continue
            seen.append(name)
            if isinstance(cmd, MethodCommand):
                kinds = cmd.kinds
                assert list(choices) == [n for n in registry.names() if registry.get(n).kind in kinds], name
                assert "toy" in choices or registry.ITERATIVE not in kinds
                assert param.default == choices[0], name  # the registry's default method
            else:
                known = {*registry.labels(), *registry.names()} - {"toy"}
                assert set(choices) - {"toy"} == known, name  # "toy" too when imported with it registered
    assert {"recon", "sweep", "recon-batch", "bench"} <= set(seen)


def _table(text: str, heading: str) -> list[list[str]]:
    part = text.split(heading, 1)[1].split("\n## ", 1)[0]
    rows = [ln for ln in part.splitlines() if ln.startswith("|")][2:]
    return [[c.strip() for c in row.strip("|").split("|")] for row in rows]


def test_the_methods_table_in_docs_is_the_registry():
    rows = _table((REPO / "docs" / "methods.md").read_text(), "## The methods")
    assert [r[0].strip("`") for r in rows] == list(registry.names())
    for row in rows:
        entry = registry.get(row[0].strip("`"))
        assert row[1] == entry.kind
        presets = re.findall(r"`([^`]+)`", row[2])
        assert presets == (list(entry.presets) if entry.named_presets else []), row


def test_backends_are_one_table():
    """rngcam.backends is the table: the rig's names, the factory and `doctor` read it; a second
    list (as in `rngcam devices` without a rig: what it lists needs no network) names only
    backends in it."""
    from rngcam import backends

    for table in (backends.CAMERAS, backends.GENERATORS):
        for name, spec in table.items():
            assert spec.name == name and (spec.twin_of is None or spec.twin_of in table)
    source = (PACKAGE / "cli" / "capture.py").read_text()
    listed = set(re.findall(r'\["(\w[\w-]*)"\]', source))
    assert listed and listed <= set(backends.CAMERAS)


def test_generator_dialects_are_one_set():
    """The driver's dialect classes, the instrument definitions (generators.yaml, one simulated
    resource each) and the rig file's type name the same dialects. The rig file's type is a
    second spelling because rngcam.config sits below acquire (docs/design.md, "Layers")."""
    from rngcam.acquire.generator import DIALECTS
    from rngcam.acquire.instruments import DEFINITIONS, dialects
    from rngcam.config import Dialect

    assert set(DIALECTS) == set(dialects()) == set(typing.get_args(Dialect))
    resources = {r["device"] for r in yaml.safe_load(DEFINITIONS.read_text())["resources"].values()}
    assert resources == set(DIALECTS)
