"""Command line: ``snaps-graph synth | run | eval | compare | demo`` (thin: parse, call, print)."""

from __future__ import annotations

import sys

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Stereo visual SLAM with SNAPS loop closure and a GTSAM pose graph.")


def main() -> None:
    from .errors import SnapsGraphError

    try:
        app()
    except SnapsGraphError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
