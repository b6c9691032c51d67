"""Command-line options generated from the registry's settings dataclasses.

Each documented settings field (rngcam.recon.options.setting) that its method offers as a flag
(registry.MethodEntry.flags) becomes one option; a name shared by several methods (--beta, --psi, ...)
is one option whose help says what it means for each. A method's other settings are `--set STAGE.KEY=VALUE`
(and `--recipe FILE.yaml`), stfm's every one (rngcam.recon.methods.stfm.setting_names). The options are made
when a command parses or shows its help, so a method registered later (a plug-in, a test's toy method) has
its options too.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from pathlib import Path

import click

from rngcam.errors import ConfigError
from rngcam.recon import registry
from rngcam.recon.options import cli_name, documented_fields
from rngcam.untrusted import read_untrusted


def _field_type(entry: registry.MethodEntry, f: dataclasses.Field):
    """The field's type without None (float | None -> float)."""
    hint = typing.get_type_hints(entry.settings_type)[f.name]
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    return args[0] if args else hint


def _shown(value) -> str:
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    return f"{value:g}" if isinstance(value, float) else str(value)


def _default_text(entry: registry.MethodEntry, f: dataclasses.Field) -> str:
    if f.metadata.get("shown_default"):
        return f.metadata["shown_default"]
    values = {p: getattr(s, f.name) for p, s in entry.presets.items()}
    # a preset that chooses another per scene (stfm's auto) leaves these unset: show the others
    values = {p: v for p, v in values.items() if v is not None} or values
    if len(set(map(repr, values.values()))) == 1 or not entry.named_presets:
        return _shown(next(iter(values.values())))
    if all(str(v) == p for p, v in values.items()):  # presets named after this setting's values
        return "the preset's: " + " or ".join(values)
    return ", ".join(f"{p} {_shown(v)}" for p, v in values.items())


def _help(pairs, listed: bool = False) -> str:
    """Per method, what the option means, its unit and its default; methods that agree share a line."""
    texts: dict[str, list[str]] = {}
    for entry, f in pairs:
        unit = f" ({f.metadata['unit']})" if f.metadata.get("unit") else ""
        texts.setdefault(f"{f.metadata['help']}{unit} [{_default_text(entry, f)}]", []).append(entry.name)
    head = "comma-separated values: " if listed else ""
    return head + "; ".join(f"{', '.join(names)}: {text}" for text, names in texts.items())


def _entries(kinds: tuple[str, ...]) -> list[registry.MethodEntry]:
    return [registry.REGISTRY[n] for n in registry.names() if registry.REGISTRY[n].kind in kinds]


def option_fields(kinds: tuple[str, ...], sweep: bool = False) -> dict[str, list[tuple[registry.MethodEntry,
                                                                                      dataclasses.Field]]]:
    """Option name -> the (method, field) pairs it sets, over the methods of `kinds`: the fields each
    method offers as flags, or with `sweep` every sweepable one (a sweep grids them; --set sets one)."""
    out: dict[str, list] = {}
    for entry in _entries(kinds):
        for f in documented_fields(entry.settings_type):
            if f.metadata.get("sweep") if sweep else entry.flagged(f.name):
                out.setdefault(cli_name(f), []).append((entry, f))
    return out


def _option(name: str, pairs) -> click.Option:
    """One generated option; its type comes from the first method's field (they must agree)."""
    entry, f = pairs[0]
    kind = _field_type(entry, f)
    for other, g in pairs[1:]:
        if _field_type(other, g) is not kind:
            raise TypeError(f"--{name} is a {kind.__name__} in {entry.name} but not in {other.name}")
    dest = name.replace("-", "_")
    text = _help(pairs)
    if kind is bool:
        values = [getattr(s, g.name) for e, g in pairs for s in e.presets.values()]
        if all(g.default is False for _, g in pairs) and not any(values):  # a flag that turns something on
            return click.Option([f"--{name}", dest], is_flag=True, default=None, flag_value=True, help=text)
        return click.Option([f"--{name}/--no-{name}", dest], default=None, help=text)
    choices = sorted({c for _, g in pairs for c in (g.metadata.get("choices") or ())})
    if choices:
        return click.Option([f"--{name}", dest], type=click.Choice(choices), default=None, help=text)
    return click.Option([f"--{name}", dest], type=kind, default=None, help=text)


def _preset_option(kinds: tuple[str, ...]) -> click.Option | None:
    entries = [e for e in _entries(kinds) if e.named_presets]
    if not entries:
        return None
    choices = sorted({p for e in entries for p in e.presets})
    text = "; ".join(f"{e.name}: {', '.join(e.presets)} [{e.default_preset}]" for e in entries)
    return click.Option(["--preset"], type=click.Choice(choices), default=None,
                        help=f"Named settings of the method, which the options below adjust. {text}.")


def method_option(kinds: tuple[str, ...], default: str | None = None) -> click.Option:
    """--method: the registry's methods of `kinds`; the default is the registry's first (its default)."""
    names = [e.name for e in _entries(kinds)]
    return click.Option(["--method"], type=click.Choice(names), default=default or names[0], show_default=True,
                        help="The reconstruction method (rngcam.recon.registry).")


def generated_options(kinds: tuple[str, ...]) -> list[click.Option]:
    """--preset and every documented setting of the methods of `kinds`."""
    preset = _preset_option(kinds)
    return [*([preset] if preset else []), *(_option(n, p) for n, p in option_fields(kinds).items())]


def _values(ctx, param, text: str | None) -> list[float] | None:
    """'10,100,1e3' -> [10.0, 100.0, 1000.0]."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise click.BadParameter(f"expected comma-separated numbers, got {text!r}") from None
    if not values or not all(math.isfinite(v) and v >= 0 for v in values):
        raise click.BadParameter(f"expected finite numbers >= 0, got {text!r}")
    return values


def sweep_options(kinds: tuple[str, ...]) -> list[click.Option]:
    """--preset and one comma-separated list option per sweepable setting."""
    out = []
    for name, pairs in option_fields(kinds, sweep=True).items():
        if pairs:
            out.append(click.Option([f"--{name}", name.replace("-", "_")], callback=_values, default=None,
                                    help=f"{_help(pairs, listed=True)} (e.g. 10,100,1000)"))
    preset = _preset_option(kinds)
    return [*([preset] if preset else []), *out]


class MethodCommand(click.Command):
    """A command whose --method and method options come from the registry when it runs."""

    def __init__(self, *args, kinds: tuple[str, ...] = (registry.ITERATIVE, registry.GS_ONLY),
                 sweep: bool = False, **kwargs):
        super().__init__(*args, **kwargs)
        self.kinds, self.sweep = kinds, sweep

    def get_params(self, ctx):
        arguments = [p for p in self.params if isinstance(p, click.Argument)]
        options = [p for p in self.params if not isinstance(p, click.Argument)]
        made = sweep_options(self.kinds) if self.sweep else generated_options(self.kinds)
        return [*arguments, method_option(self.kinds), *options, *made, *super().get_params(ctx)[len(self.params):]]

    def parse_args(self, ctx, args):
        try:
            return super().parse_args(ctx, args)
        except click.NoSuchOption as exc:  # a setting that is not a flag: say its --set spelling
            instead = None if self.sweep else set_instead(exc.option_name, self.kinds)
            if instead is None:
                raise
            raise click.UsageError(f"no option {exc.option_name}: {instead}", ctx) from None


def set_instead(option: str, kinds: tuple[str, ...]) -> str | None:
    """How to give the setting of an option a method does not offer (--base -> 'set stfm's dynamic_base with
    --set fit.base=VALUE'); None if no method has such a setting."""
    for entry in _entries(kinds):
        for f in documented_fields(entry.settings_type):
            name = cli_name(f)
            if entry.flagged(f.name) or f.name not in entry.set_names or option not in (f"--{name}", f"--no-{name}"):
                continue
            value = ("false" if option.startswith("--no-") else "true") if _field_type(entry, f) is bool else "VALUE"
            return f"set {entry.name}'s {f.name} with --set {entry.set_names[f.name]}={value}"
    return None


def method_command(name: str, **kwargs):
    """`@method_command("recon")`: a click command with the registry's options (see MethodCommand)."""
    return click.command(name, cls=MethodCommand, **kwargs)


def pop_method_values(params: dict) -> dict:
    """The generated options given on the command line (a command's **kwargs hold only those)."""
    given = {k: v for k, v in params.items() if v is not None}
    params.clear()
    return given


def stage_options(f):
    """--set and --recipe (`stage_values`, `recipe_file`): a method's settings by stage (see method_settings)."""
    f = click.option("--recipe", "recipe_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
                     help="stfm: a YAML file of stage settings (stage: {key: value}), applied before the "
                          "options and --set.")(f)
    return click.option(
        "--set", "stage_values", multiple=True, metavar="STAGE.KEY=VALUE",
        help="stfm: set one setting of one stage of the recipe, a number of the stage's own or a setting it owns "
             "(repeatable; --explain lists each stage's), e.g. --set fit.tau=1e-4, --set line_refit.enabled=false, "
             "--set self_calibration.mode=all.")(f)


def method_settings(method: str, given: dict, assignments: tuple[str, ...] = (), recipe_file: Path | None = None):
    """The settings of `method` from its preset, a --recipe file, the options given (by option destination)
    and --set STAGE.KEY=VALUE, each over the one before; an option that does not apply to it, or a bad
    --set or recipe, is one usage line."""
    entry = registry.get(method)
    preset = given.pop("preset", None)
    documented = {cli_name(f).replace("-", "_"): f.name for f in documented_fields(entry.settings_type)}
    fields = {dest: name for dest, name in documented.items() if entry.flagged(name)}
    bad = sorted(set(given) - set(fields))
    if preset is not None and (not entry.named_presets or preset not in entry.presets):
        bad.insert(0, "preset")
    if bad:
        names = ", ".join("--" + b.replace("_", "-") for b in bad)
        choices = f" (its presets: {', '.join(entry.presets)})" if bad[0] == "preset" and entry.named_presets else ""
        spelled = [f"--set {entry.set_names[documented[b]]}=..." for b in bad if documented.get(b) in entry.set_names]
        instead = f"; use {', '.join(spelled)}" if spelled else ""
        raise click.UsageError(f"{names} does not apply to --method {method}{choices}{instead}")
    flags = {fields[k]: v for k, v in given.items()}
    settings = entry.settings(preset, **flags)
    if not assignments and recipe_file is None:
        return settings
    if entry.with_stages is None:
        raise click.UsageError(f"--set and --recipe do not apply to --method {method} (it has no stages)")
    overrides = _assigned(assignments)
    named = {f"{stage}.{key}" for stage, keys in overrides.items() for key in keys}
    for dest in given:
        if entry.set_names.get(fields[dest]) in named:
            raise click.UsageError(f"--{dest.replace('_', '-')} and --set {entry.set_names[fields[dest]]} both set "
                                   f"{fields[dest]}: give one")
    try:
        if recipe_file is not None:  # the file under the options: the command line has the last word
            settings = dataclasses.replace(entry.with_stages(entry.settings(preset), _recipe(recipe_file)), **flags)
        return entry.with_stages(settings, overrides) if overrides else settings
    except ConfigError as exc:
        raise click.UsageError(str(exc).removeprefix("stfm: ")) from None


def _assigned(assignments: tuple[str, ...]) -> dict:
    """--set STAGE.KEY=VALUE ... -> {stage: {key: value}} (one usage line for one not so spelled)."""
    overrides: dict = {}
    for item in assignments:
        name, eq, value = item.partition("=")
        stage, dot, key = name.strip().partition(".")
        if not (eq and dot and stage and key):
            raise click.BadParameter(f"{item!r} is not STAGE.KEY=VALUE", param_hint="--set")
        overrides.setdefault(stage, {})[key] = value.strip()
    return overrides


def _recipe(path: Path) -> dict:
    """A --recipe file's stage settings (read as untrusted input; one line naming it when bad)."""
    from rngcam.recon.methods.stfm.recipe import MAX_RECIPE_CHARS, recipe_from_yaml  # heavy: torch

    return recipe_from_yaml(read_untrusted(path, MAX_RECIPE_CHARS).decode("utf-8", "replace"), str(path))
