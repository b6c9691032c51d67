"""The README's command reference against the command line itself (click's command tree, with
the options each command makes when it parses): every command and every option is there, no
option is there that the command lacks, and every choice list is the command's. A new option
needs one README entry; this test names it. Also: shell completion works as the README says."""

from __future__ import annotations

import re
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from rngcam.cli import main

README = Path(__file__).resolve().parents[1] / "README.md"


def commands() -> dict[str, click.Command]:
    """'calibrate psf' -> its command, for every leaf command of `rngcam`."""
    out = {}

    def walk(cmd, path, ctx):
        if isinstance(cmd, click.Group):
            for name in cmd.list_commands(ctx):
                sub = cmd.get_command(ctx, name)
                if sub is not None:
                    walk(sub, [*path, name], click.Context(sub, parent=ctx, info_name=name))
        else:
            out[" ".join(path)] = (cmd, ctx)

    walk(main, [], click.Context(main, info_name="rngcam"))
    return out


def options(cmd: click.Command, ctx: click.Context) -> dict[str, click.Option]:
    """Every long option name (both halves of --x/--no-x) -> its option, --help left out."""
    out = {}
    for p in cmd.get_params(ctx):
        if isinstance(p, click.Option) and "--help" not in p.opts:
            for name in (*p.opts, *p.secondary_opts):
                if name.startswith("--"):
                    out[name] = p
    return out


def reference_rows() -> dict[str, str]:
    """The command reference table: 'calibrate psf' -> the rest of its row."""
    text = README.read_text()
    section = text.split("## Command reference", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        m = re.match(r"\| `rngcam ([a-z-]+(?: [a-z-]+)?)[^`]*` \|(.*)", line)
        if m:
            rows[m.group(1).strip()] = m.group(2).replace("\\|", "|")
    return rows


def test_every_command_has_a_row_and_every_row_a_command():
    rows, cmds = reference_rows(), commands()
    assert sorted(rows) == sorted(cmds), (sorted(set(cmds) - set(rows)), sorted(set(rows) - set(cmds)))


@pytest.mark.parametrize("name", sorted(commands()))
def test_every_option_is_in_the_reference_and_nothing_stale(name):
    cmd, ctx = commands()[name]
    row = reference_rows()[name]
    opts = options(cmd, ctx)
    listed = set(re.findall(r"(?<![\w-])(--[a-z0-9][a-z0-9-]*)", row))
    missing = sorted(set(opts) - listed)
    assert not missing, f"README's `rngcam {name}` row lacks {missing}"
    stale = sorted(listed - set(opts) - {"--help"})
    assert not stale, f"README's `rngcam {name}` row names options it does not have: {stale}"
    # a choice list written out (`--opt a|b|c`) is exactly the option's choices
    for opt, values in re.findall(r"`(--[a-z0-9-]+) ([A-Za-z0-9_]+(?:\|[A-Za-z0-9_]+)+)`", row):
        option = opts[opt]
        if isinstance(option.type, click.Choice):
            assert set(values.split("|")) == set(option.type.choices), (name, opt, values)


def test_shell_completion_works_as_documented():
    text = README.read_text()
    assert "_RNGCAM_COMPLETE=bash_source rngcam > ~/.rngcam-complete.bash" in text
    res = CliRunner().invoke(main, [], prog_name="rngcam", env={"_RNGCAM_COMPLETE": "bash_source"})
    assert res.exit_code == 0 and "_rngcam_completion" in res.output and "complete " in res.output
    res = CliRunner().invoke(main, [], prog_name="rngcam",
                             env={"_RNGCAM_COMPLETE": "bash_complete", "COMP_WORDS": "rngcam rep", "COMP_CWORD": "1"})
    assert "plain,report" in res.output.replace("\n", ",")


def test_the_walkthrough_commands_exist():
    """Each `rngcam ...` command the walkthrough and the Python section name is a real command."""
    text = README.read_text()
    walk = text.split("## Five minutes with rngcam", 1)[1].split("\n## On real hardware", 1)[0]
    used = set(re.findall(r"`rngcam ([a-z-]+)", walk))
    cmds = {name.split()[0] for name in commands()}
    assert used and used <= cmds, used - cmds
