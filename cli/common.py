"""What every command shares: one console, and bad input turned into one clear line and exit 1."""

from __future__ import annotations

import functools
from typing import Callable, TypeVar

import typer
from rich.console import Console
from rich.text import Text

from d3lvo_deploy.errors import D3LVOInputError

def _console(stderr: bool) -> Console:
    """Piped or redirected, rich would cut tables to 80 columns (`100.5…` for an ATE): wide enough
    there that every cell stays whole. No markup: paths and user input go into most lines, and rich
    would read `[v2]` in a folder name as a style (and `[/]` as an error after the work is done);
    a coloured word is a `Text` (`lead`)."""
    c = Console(stderr=stderr, markup=False, emoji=False)  # `:cat:` in a path stays as typed
    return c if c.is_terminal else Console(stderr=stderr, width=200, markup=False, emoji=False)


def lead(word: str, style: str, text: str = "") -> Text:
    """`word` in `style`, then `text` as it is."""
    return Text.assemble((word, style), text)


console = _console(stderr=True)  # tables and progress go to stderr so --json stdout stays parseable
out = _console(stderr=False)


def note_oversubscribed(threads: int) -> None:
    """More threads than cores only take turns on them: each frame slower, not faster. The cores
    are those the engines count by default (`backends.usable_cores`)."""
    from d3lvo_deploy.backends import usable_cores

    cores = usable_cores()
    if threads > cores:
        console.print(lead("note", "yellow", f" --threads {threads} is more than the {cores} cores this process "
                                             "may use: the threads take turns on them, and each frame takes longer"),
                      highlight=False)


F = TypeVar("F", bound=Callable)


def friendly_errors(fn: F) -> F:
    """Bad input -> `error: <file>: <problem>` and exit code 1, never a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except D3LVOInputError as e:
            console.print(lead("error:", "bold red", f" {e}"), highlight=False, soft_wrap=True)
            raise typer.Exit(1) from None
        except KeyboardInterrupt:
            console.print(lead("interrupted", "yellow"))
            raise typer.Exit(130) from None

    return wrapper  # type: ignore[return-value]


def given_on_command_line(ctx: typer.Context, name: str) -> bool:
    """Whether option `name` was typed, not defaulted: a `--config` file fills only the others.
    Compared by name, since typer may bring its own copy of click's ParameterSource."""
    return getattr(ctx.get_parameter_source(name), "name", "DEFAULT") not in ("DEFAULT", "DEFAULT_MAP")
