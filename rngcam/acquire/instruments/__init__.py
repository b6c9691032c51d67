"""The function generators' command sets as data (generators.yaml, pyvisa-sim's format), and a
small reader of that format for rngcam's own fake instrument, so the pty fake and pyvisa-sim hold
the driver to the same definitions.

`instrument(dialect)` gives an `InstrumentDef`: its exact dialogues (per channel where the text
holds `{ch_id}`), its per-channel property setters as regular expressions with their specs, and
its error queue. `InstrumentDef.apply(command)` returns what the instrument does with one
command: ("answer", text), ("set", channel, property, value), ("do", channel, command text) for
a write-only dialogue, or ("error", code_and_message) for anything outside the command set.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

DEFINITIONS = Path(__file__).with_name("generators.yaml")


@dataclass
class PropertyDef:
    name: str
    pattern: re.Pattern
    type: type
    default: object
    minimum: float | None = None
    maximum: float | None = None
    valid: tuple | None = None

    def convert(self, text: str):
        """The value as the instrument takes it; ValueError outside the specs."""
        value = self.type(text)
        if self.valid is not None and value not in self.valid:
            raise ValueError(f"{value!r} not one of {self.valid}")
        if self.minimum is not None and value < self.minimum:
            raise ValueError(f"{value} below {self.minimum}")
        if self.maximum is not None and value > self.maximum:
            raise ValueError(f"{value} above {self.maximum}")
        return value


@dataclass
class InstrumentDef:
    name: str
    resource: str
    idn: str
    error_query: str
    no_error: str
    command_error: str
    dialogues: dict[str, str | None] = field(default_factory=dict)  # exact text -> answer (None: write-only)
    channel_dialogues: list[tuple[re.Pattern, str]] = field(default_factory=list)
    properties: list[PropertyDef] = field(default_factory=list)
    channels: tuple[int, ...] = (1, 2)

    def defaults(self) -> dict[str, object]:
        return {p.name: p.default for p in self.properties}

    def apply(self, command: str):
        """What the instrument does with `command` (module doc)."""
        if command in self.dialogues:
            answer = self.dialogues[command]
            return ("do", None, command) if answer is None else ("answer", answer)
        for pattern, text in self.channel_dialogues:
            m = pattern.fullmatch(command)
            if m and int(m["ch"]) in self.channels:
                return ("do", int(m["ch"]), text)
        for prop in self.properties:
            m = prop.pattern.fullmatch(command)
            if not m or int(m["ch"]) not in self.channels:
                continue
            try:
                return ("set", int(m["ch"]), prop.name, prop.convert(m["v"]))
            except ValueError:
                continue  # another setter may take this text (pyvisa-sim tries them all too)
        return ("error", self.command_error)


def _template(text: str) -> re.Pattern:
    """pyvisa-sim's '{ch_id}' and '{:s}' fields as named regex groups; the rest literal."""
    out, pos = [], 0
    for m in re.finditer(r"\{ch_id\}|\{:s\}", text):
        out.append(re.escape(text[pos:m.start()]))
        out.append(r"(?P<ch>\d+)" if m.group() == "{ch_id}" else r"(?P<v>.+)")
        pos = m.end()
    out.append(re.escape(text[pos:]))
    return re.compile("".join(out))


@functools.cache
def _load() -> dict:
    return yaml.safe_load(DEFINITIONS.read_text(encoding="utf-8"))


def instrument(dialect: str) -> InstrumentDef:
    """The definition of one dialect's instrument; KeyError when there is none."""
    data = _load()
    dev = data["devices"][dialect]
    resource = next(r for r, d in data["resources"].items() if d["device"] == dialect)
    queue = dev["error"]["error_queue"][0]
    dialogues = {d["q"]: d.get("r") for d in dev.get("dialogues", [])}
    out = InstrumentDef(dialect, resource, dialogues.get("*IDN?", ""), queue["q"], queue["default"],
                        queue["command_error"], dialogues)
    types = {"float": float, "int": int, "str": str}
    for ch in dev.get("channels", {}).values():
        out.channels = tuple(int(i) for i in ch["ids"])
        for d in ch.get("dialogues", []):
            out.channel_dialogues.append((_template(d["q"]), d["q"]))
        for name, p in ch.get("properties", {}).items():
            specs = p.get("specs", {})
            t = types[specs.get("type", "str")]
            valid = tuple(t(v) for v in specs["valid"]) if "valid" in specs else None
            bounds = [None if specs.get(k) is None else float(specs[k]) for k in ("min", "max")]
            out.properties.append(PropertyDef(name, _template(p["setter"]["q"]), t, t(p["default"]), *bounds, valid))
    return out


def dialects() -> list[str]:
    return list(_load()["devices"])
