"""What the command line shows and how it ends: progress, the run summary, Ctrl-C and a failed
standard output. The commands themselves live in :mod:`snaps_graph.cli`."""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import sys
import time
from pathlib import Path

import typer

from .errors import note_interrupt
from .io_utils import committed_folders, parse_frame_range
from .types import StereoSource

EXIT_USER_ERROR = 2
EXIT_MOSTLY_FLAGGED = 3
EXIT_CELLS_FAILED = 4
EXIT_INTERRUPTED = 130

# A progress line this often when stderr is not a terminal (logs, CI); a shorter run prints none,
# so its stderr holds only notes, warnings and errors.
LOG_EVERY_S = 10.0


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class Progress:
    """Frames done, rate and ETA on stderr: a tqdm bar on a terminal, else one plain line every
    ``LOG_EVERY_S`` seconds (and one at the end). ``phase`` names what runs after the last frame
    (the bar closes at the last frame, so its rate is the one the summary prints: :attr:`rate`)."""

    def __init__(self, total: int | None, desc: str, stream=None):
        self.total, self.desc, self.n = total, desc, 0
        self.stream = stream if stream is not None else sys.stderr
        self._postfix: dict = {}
        self._done = False
        self._printed_n = -1
        self._printed = False  # a plain line was printed: the run is long, its end is reported too
        self._bar = None
        if self.stream.isatty():
            from tqdm import tqdm

            # smoothing=0: the bar's rate is the average, the figure the summary prints
            self._bar = tqdm(
                total=total, desc=desc, unit="frame", dynamic_ncols=True, file=self.stream, mininterval=0.5, smoothing=0
            )
        self._tty = self._bar is not None
        self.t0 = time.perf_counter()  # after the bar is made: both rates count from here
        self.t_last = self._logged = self.t0

    @property
    def rate(self) -> float | None:
        """Frames per second from the start to the last frame, wall clock."""
        dt = self.t_last - self.t0
        return self.n / dt if self.n and dt > 0 else None

    def set_postfix(self, refresh: bool = False, **kw) -> None:
        self._postfix.update(kw)
        if self._bar is not None:
            self._bar.set_postfix(refresh=refresh, **kw)

    def update(self, n: int = 1) -> None:
        self.n += n
        self.t_last = time.perf_counter()
        if self._bar is not None:
            self._bar.update(n)
        elif self.t_last - self._logged >= LOG_EVERY_S:
            self._logged = self.t_last
            self._line()
        if self.total is not None and self.n >= self.total:
            self._close_bar()

    def phase(self, label: str) -> None:
        """Work after the frames (optimisation, map, pictures): one line naming it."""
        self._close_bar()
        if self._tty or self._printed:
            print(f"{self.desc}: {label} ...", file=self.stream, flush=True)

    def _line(self) -> None:
        rate = self.rate
        done = f"{self.n}/{self.total}" if self.total else str(self.n)
        eta = f", ETA {_clock((self.total - self.n) / rate)}" if rate and self.total and self.n < self.total else ""
        extra = "".join(f", {k} {v}" for k, v in self._postfix.items())
        print(f"{self.desc}: {done} frames, {rate or 0:.1f} frames/s{eta}{extra}", file=self.stream, flush=True)
        self._printed, self._printed_n = True, self.n

    def _close_bar(self) -> None:
        if self._done:
            return
        self._done = True
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        elif self._printed and self._printed_n != self.n:
            self._line()  # the final rate, as the summary gives it

    def close(self) -> None:
        self._close_bar()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress(total: int | None, desc: str) -> Progress:
    return Progress(total, desc)


def fmt(v, nd=3) -> str:
    if v is None or (isinstance(v, float) and v != v):
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def metrics_table(per_traj: dict[str, dict]) -> str:
    head = (
        f"{'trajectory':<14}{'frames':>8}{'mean dev m':>12}{'horiz':>8}{'vert':>8}{'ATE m':>10}{'t_rel %':>9}"
        f"{'r_rel °/100m':>14}{'end drift %':>13}"
    )
    lines = [head, "-" * len(head)]
    for name, m in per_traj.items():
        lines.append(
            f"{name:<14}{m.get('frames', ''):>8}{fmt(m.get('mean_deviation')):>12}"
            f"{fmt(m.get('mean_deviation_horizontal')):>8}{fmt(m.get('mean_deviation_vertical')):>8}{fmt(m.get('ate_rmse')):>10}"
            f"{fmt(m.get('t_rel'), 2):>9}{fmt(m.get('r_rel'), 3):>14}{fmt(m.get('end_drift_percent'), 2):>13}"
        )
    from .evaluation.metrics import notes_text

    lines += [f"note: {line}" for line in notes_text(per_traj)]
    return "\n".join(lines)


def loops_text(metrics: dict, verb: str = "") -> str:
    """ "12 loops (4 corrected the heuristic)": the others are the graph's only. ``verb`` goes
    after the count ("12 loops closed (4 ...)")."""
    n, c = metrics["loops"], metrics.get("loops_corrected")
    return f"{n} loops{' ' + verb if verb else ''}" + (f" ({c} corrected the heuristic)" if c is not None and c != n else "")


def print_summary(metrics: dict, out: Path, wall_rate: float | None = None, partial: bool = False) -> None:
    """The run's summary. ``wall_rate``: frames/s on the wall clock over the frames (the progress
    line's); ``partial``: a ``--frames`` range (its ground truth is poses_gt.txt, not the official file)."""
    lat = metrics.get("latency_ms", {})
    fps = lat.get("frames_per_s")
    typer.echo(
        f"{metrics['frames']} frames ({metrics.get('flagged_frames', 0)} flagged), {loops_text(metrics)}, "
        f"median {fmt(lat.get('total', {}).get('median'), 1)} ms/frame"
        + (f" ({fps:.1f} frames/s processing)" if fps else "")
        + (f", wall {wall_rate:.1f} frames/s" if wall_rate else "")
    )
    if "trajectories" in metrics:
        typer.echo(metrics_table(metrics["trajectories"]))
    if "map" in metrics and "error" in metrics["map"]:
        typer.echo(f"warning: no map (the map stage failed: {metrics['map']['error']}); the trajectories are written", err=True)
    elif "map" in metrics:
        typer.echo(
            f"map: {metrics['map']['keyframes']} keyframes, {metrics['map']['bytes'] / 2**20:.0f} MiB of stored depth, fused under {metrics['map']['trajectory']}"
        )
    typer.echo(f"peak memory {metrics.get('peak_rss_mb', 0):.0f} MiB")
    if metrics.get("graph_failures"):
        typer.echo(f"graph: {len(metrics['graph_failures'])} flagged updates (see metrics.json)")
    graph = metrics.get("graph", {})
    doubtful = graph.get("consistency", {}).get("doubtful")
    if doubtful:
        typer.echo(f"warning: the refined trajectory is doubtful: {doubtful} (metrics.json, graph.consistency)", err=True)
    if graph.get("batch_stop", "converged") not in ("converged", ""):
        typer.echo(f"warning: the batch solve stopped at the {graph['batch_stop']} (metrics.json, graph)", err=True)
    typer.echo(f"results in {out}")
    if (out / "poses_gt.txt").is_file():
        which = "the ground truth of exactly these frames, re-based" if partial else "the ground truth, re-based"
        typer.echo(f"  evo: evo_ape kitti {out / 'poses_gt.txt'} {out / 'poses_vo.txt'} -a   ({which})")
    if not (out / "report.md").is_file():
        typer.echo(f"  report and pictures: snaps-graph compare {out}")


def print_input_notes(seq: StereoSource, frames: str | None, topics_given: bool = False) -> None:
    """What a reader dropped or assumed (unpaired images, frames without ground truth), a range
    beyond the sequence's end (it runs to the end; a start past it is an error), and a bag's
    stereo topics when they were found by name."""
    for note in seq.notes:
        typer.echo(f"note: {note}", err=True)
    rng = parse_frame_range(frames)
    n = len(seq)
    if rng is not None and rng[1] is not None and rng[1] - rng[0] > n:
        typer.echo(f"note: --frames {frames}: the sequence has {rng[0] + n} frames; running {rng[0]}:{rng[0] + n}", err=True)
    info = seq.source_info
    if info.get("left_topic") and not topics_given:
        right = f", right {info['right_topic']}" if info.get("right_topic") else ""
        typer.echo(f"topics: left {info['left_topic']}{right} (found by name; --left-topic / --right-topic choose others)")


def warn_mostly_flagged(metrics: dict) -> None:
    print(
        f"warning: the front end flagged {metrics['flagged_frames']} of {metrics['frames']} frames "
        f"(their poses are constant-velocity guesses); exit status {EXIT_MOSTLY_FLAGGED}",
        file=sys.stderr,
    )


class Interrupted(BaseException):
    """Ctrl-C, raised by our SIGINT handler: click turns a KeyboardInterrupt into "Aborted!", so
    SIGINT raises this instead, which passes through click (and through every
    ``except Exception``) to ``cli.main``; cleanup handlers (``except BaseException``) still run."""


def on_sigint(signum, frame) -> None:
    note_interrupt()
    raise Interrupted()


STDOUT_ERRNOS = (errno.ENOSPC, errno.EPIPE, errno.EIO, errno.EDQUOT, errno.EFBIG)


def stdout_failed(exc: OSError) -> None:
    """Standard output cannot be written (a full device, a closed pipe): say so on stderr; the
    results folder, when it was completed, stands (exit 0)."""
    with contextlib.suppress(OSError):  # no second failure at the interpreter's final flush
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    done = committed_folders()
    if done:
        print(
            f"note: standard output not written ({exc.strerror}); the results are complete in {', '.join(map(str, done))}",
            file=sys.stderr,
        )
        sys.exit(0)
    print(f"error: cannot write to standard output ({exc.strerror or exc})", file=sys.stderr)
    sys.exit(EXIT_USER_ERROR)


_REPLACING: list[Path] = []  # earlier results an --overwrite run would replace at its end


def replacing(folder: Path, overwrite: bool) -> None:
    """Note that ``folder`` holds earlier results this run replaces only when it completes, so a
    Ctrl-C before then can say they were kept."""
    if overwrite and folder.is_dir() and any(folder.iterdir()):
        _REPLACING.append(folder)


def exit_interrupted() -> None:
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # a second Ctrl-C or kill must not interrupt the exit
        signal.signal(sig, signal.SIG_IGN)
    done = committed_folders()
    kept = [p for p in _REPLACING if p.resolve() not in {d.resolve() for d in done}]
    also = f"; the earlier results in {', '.join(map(str, kept))} are kept as they were" if kept else ""
    if done:
        print(f"interrupted after the results were written: {', '.join(map(str, done))} complete{also}", file=sys.stderr)
    elif kept:
        print(f"interrupted: no new results written{also}", file=sys.stderr)
    else:
        print("interrupted: no results written", file=sys.stderr)
    with contextlib.suppress(Exception):
        sys.stdout.flush()
        sys.stderr.flush()
    # Cleanup ran on the way here; exit now: the finalizers of a library whose import the
    # Ctrl-C cut (open3d) would print pages and change the status.
    os._exit(EXIT_INTERRUPTED)
