"""The `d3lvo` command line (typer + rich)."""
