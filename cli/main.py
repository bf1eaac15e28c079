"""Entry point of the `d3lvo` command."""

from __future__ import annotations

import inspect

import typer

from .bench_cmd import bench_command
from .demo_cmd import demo_command
from .eval_cmd import eval_command
from .export_cmd import export_command
from .parity_cmd import parity_command
from .run_cmd import run_command
from .synth_cmd import synth_command
from .train_cmd import train_command

app = typer.Typer(
    name="d3lvo",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version(value: bool) -> None:
    if value:
        from d3lvo_deploy import __version__

        typer.echo(f"d3lvo-deploy {__version__}")
        raise typer.Exit()


@app.callback()
def root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                      help="Print the version and exit.")) -> None:
    """D3LVO LiDAR-visual odometry: train in PyTorch, export to ONNX, run on a CPU without torch.

    The commands in the order of the work: demo (everything once, on the bundled model), synth
    (KITTI-format synthetic drives), train, export (the ONNX stages), parity (ONNX against
    torch), run (odometry on a KITTI sequence or raw drive, a ROS bag or a folder of scans), eval
    (KITTI devkit scores), bench (speed on this CPU).
    Example: d3lvo run drive.mcap   (poses, metrics and latency in results/latest/)
    """


def one_line_paragraphs(doc: str) -> str:
    """Typer's rich help keeps a docstring's line breaks, which then wrap raggedly in a narrow
    terminal: each paragraph on one line for rich to wrap (an `Example:` line stays its own)."""
    paragraphs = []
    for paragraph in inspect.cleandoc(doc).split("\n\n"):
        lines: list[str] = []
        for line in paragraph.splitlines():
            if lines and not line.startswith("Example:"):
                lines[-1] += " " + line.strip()
            else:
                lines.append(line.strip())
        paragraphs.append("\n".join(lines))
    return "\n\n".join(paragraphs)


root.__doc__ = one_line_paragraphs(root.__doc__)
for name, command in (("demo", demo_command), ("synth", synth_command), ("train", train_command),
                      ("export", export_command), ("parity", parity_command), ("run", run_command),
                      ("eval", eval_command), ("bench", bench_command)):
    command.__doc__ = one_line_paragraphs(command.__doc__)
    app.command(name)(command)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
