"""Entry point of the `d3lvo` command."""

from __future__ import annotations

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
    help="D3LVO LiDAR-visual odometry: synthetic KITTI data, evaluation, export and ONNX runtime.",
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
    """D3LVO LiDAR-visual odometry toolkit."""


app.command("eval")(eval_command)
app.command("synth")(synth_command)
app.command("train")(train_command)
app.command("export")(export_command)
app.command("parity")(parity_command)
app.command("run")(run_command)
app.command("bench")(bench_command)
app.command("demo")(demo_command)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
