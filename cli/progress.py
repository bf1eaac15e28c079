"""The rich progress bar every long command uses."""

from __future__ import annotations

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from .common import console


def frame_progress() -> Progress:
    return Progress(
        TextColumn("{task.description}", style="bold", markup=False),  # a description may hold a path
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[rate]}", markup=False),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
    )
