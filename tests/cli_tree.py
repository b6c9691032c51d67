"""The command line's leaf commands, for tests that walk every command."""

from __future__ import annotations

import click


def leaf_commands(group: click.Group, path: tuple[str, ...] = ()):
    """('calibrate psf', command) for every leaf command under `group`."""
    ctx = click.Context(group)
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        if isinstance(cmd, click.Group):
            yield from leaf_commands(cmd, (*path, name))
        else:
            yield " ".join((*path, name)), cmd
