"""Command-line options generated from the registry's settings dataclasses.

Each documented settings field (rngcam.recon.options.setting) becomes one option; a name shared
by several methods (--beta, --psi, ...) is one option whose help says what it means for each.
The options are made when a command parses or shows its help, so a method registered later
(a plug-in, a test's toy method) has its options too.
"""

from __future__ import annotations

import dataclasses
import math
import typing

import click

from rngcam.recon import registry
from rngcam.recon.options import cli_name, documented_fields


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


def option_fields(kinds: tuple[str, ...]) -> dict[str, list[tuple[registry.MethodEntry, dataclasses.Field]]]:
    """Option name -> the (method, field) pairs it sets, over the methods of `kinds`."""
    out: dict[str, list] = {}
    for entry in _entries(kinds):
        for f in documented_fields(entry.settings_type):
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
    for name, pairs in option_fields(kinds).items():
        pairs = [(e, f) for e, f in pairs if f.metadata.get("sweep")]
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


def method_command(name: str, **kwargs):
    """`@method_command("recon")`: a click command with the registry's options (see MethodCommand)."""
    return click.command(name, cls=MethodCommand, **kwargs)


def pop_method_values(params: dict) -> dict:
    """The generated options given on the command line (a command's **kwargs hold only those)."""
    given = {k: v for k, v in params.items() if v is not None}
    params.clear()
    return given


def method_settings(method: str, given: dict):
    """The settings of `method` from its preset and the options given (by option destination);
    an option that does not apply to it is one usage line."""
    entry = registry.get(method)
    preset = given.pop("preset", None)
    fields = {cli_name(f).replace("-", "_"): f.name for f in documented_fields(entry.settings_type)}
    bad = sorted(set(given) - set(fields))
    if preset is not None and (not entry.named_presets or preset not in entry.presets):
        bad.insert(0, "preset")
    if bad:
        names = ", ".join("--" + b.replace("_", "-") for b in bad)
        choices = f" (its presets: {', '.join(entry.presets)})" if bad[0] == "preset" and entry.named_presets else ""
        raise click.UsageError(f"{names} does not apply to --method {method}{choices}")
    return entry.settings(preset, **{fields[k]: v for k, v in given.items()})
