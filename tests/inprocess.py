"""The command line run inside the test process: ``cli("run", seq, "--out", out)`` calls
``snaps_graph.cli.main`` (what the ``snaps-graph`` script calls) with typer's test runner holding
stdin, stdout, stderr and the environment, and returns what a finished process would show.

A process costs about two seconds of imports (OpenCV, gtsam, open3d) per call; in-process the
imports are paid once. What a process alone shows (signals, the exit of the console script, locks
held between processes, the imports a command does not need) stays in subprocess tests.

The process-wide state ``main`` sets is put back after each call, so calls do not see each other:
the signal handlers, the working folder, the warnings filters, the Ctrl-C flag and the lists of
folders completed or being replaced. A call that would end the process on Ctrl-C (``os._exit``)
fails the test instead.
"""

from __future__ import annotations

import os
import signal
import sys
import traceback
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from typer.testing import CliRunner

from snaps_graph import cli as cli_module
from snaps_graph import console, errors, io_utils, locks

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@dataclass
class Ran:
    """What a finished ``snaps-graph`` process shows (the fields of ``subprocess.CompletedProcess``)."""

    args: list[str]
    returncode: int
    stdout: str
    stderr: str


def _no_exit_on_interrupt() -> None:
    raise AssertionError("the in-process run was interrupted: test Ctrl-C in a subprocess")


def cli(*args: object, cwd: str | Path | None = None, env: Mapping[str, str | None] | None = None) -> Ran:
    """``snaps-graph ARGS`` in this process: its exit status and its output."""
    argv = ["snaps-graph", *(str(a) for a in args)]
    handlers = {sig: signal.getsignal(sig) for sig in SIGNALS}
    saved = (list(io_utils._COMMITTED), list(console._REPLACING), errors.interrupted())
    old_argv, old_cwd, old_exit = sys.argv, os.getcwd(), cli_module.exit_interrupted
    io_utils._COMMITTED.clear()
    console._REPLACING.clear()
    errors._INTERRUPTED.clear()
    code: int = 0
    with CliRunner().isolation(env=env) as (out, err, _):
        sys.argv, cli_module.exit_interrupted = argv, _no_exit_on_interrupt
        try:
            if cwd is not None:
                os.chdir(cwd)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # as PYTHONWARNINGS=ignore in a subprocess test
                cli_module.main()
        except SystemExit as exc:
            if exc.code is None or isinstance(exc.code, int):
                code = exc.code or 0
            else:  # sys.exit("message"): Python prints it and exits 1
                print(exc.code, file=sys.stderr)
                code = 1
        except AssertionError:
            raise
        except Exception:  # what escapes main(): a process prints the traceback and exits 1
            traceback.print_exc()
            code = 1
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            sys.argv, cli_module.exit_interrupted = old_argv, old_exit
            os.chdir(old_cwd)
            for sig, handler in handlers.items():
                signal.signal(sig, handler)
            io_utils._COMMITTED[:] = saved[0]
            console._REPLACING[:] = saved[1]
            if not saved[2]:
                errors._INTERRUPTED.clear()
        assert not locks._HELD, f"a lock outlived the run: {list(locks._HELD)}"
        stdout, stderr = out.getvalue().decode(), err.getvalue().decode(errors="backslashreplace")
    return Ran(argv[1:], code, stdout, stderr)
