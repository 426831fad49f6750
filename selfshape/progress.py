"""The status line of the long runs (simulate, design, sweep, the law and targets studies) on a
terminal's stderr, drawn by tqdm.

The lower layers report progress through a callback (forward.simulate, inverse.design:
dicts such as {"stage": "newton", "iteration": 12, "energy": ..., "gradient_norm": ...}; a
run of independent tasks: {"stage": "tasks", "done": 3, "total": 6, "unit": "cases"});
:class:`StatusLine` turns them into one line that is rewritten in place (carriage return and
erase-line) and erased again before the verb prints its result or error, so a terminal ends
with the same lines as a pipe. Task counts show done / total and the time left (tqdm's
estimate: the tasks still to do at the mean rate since the first count, so tasks that were
already done when the run started do not count as speed). The line is shown only when stderr
is a terminal, not under CI (the ``CI`` variable), not with TERM=dumb and not with ``--quiet``
or ``-v`` (whose per-iteration lines go to stdout instead); in a pipe nothing of it is written.

It writes to its own copy of file descriptor 2 taken before the verb runs (tqdm's ``file=``),
because the CLI redirects descriptor 2 while a verb runs to keep library chatter from the
terminal. tqdm's monitor thread is off: every update is drawn synchronously by the caller, at
most ``MIN_INTERVAL_S`` apart unless the stage changes, so nothing runs beside the solver.
"""
from __future__ import annotations

import os
import sys
import threading
import time

from tqdm import tqdm

#: Least time between two redraws of the same stage, s.
MIN_INTERVAL_S = 0.1
#: Width assumed when the terminal reports 0 columns (a fresh pseudo-terminal), characters.
UNKNOWN_COLUMNS = 100
_ERASE = "\r\x1b[2K"
_EVENTS = "{desc}"
_TASKS = "{desc}{n_fmt}/{total_fmt} {unit}, {remaining} left{postfix}"


def wanted(fd: int = 2, *, quiet: bool = False, env=None) -> bool:
    """Whether a status line belongs on ``fd``: a terminal, not quiet, not CI, not TERM=dumb."""
    env = os.environ if env is None else env
    if quiet or env.get("CI", "").strip().lower() not in ("", "0", "false", "no") or env.get("TERM") == "dumb":
        return False
    try:
        return os.isatty(fd)
    except OSError:
        return False


class _Line(tqdm):
    """A tqdm bar kept to one line: drawn with erase-line (``ESC [2K``) rather than tqdm's
    padding with spaces, so that erasing it leaves exactly ``\\r ESC [2K`` and nothing of it on
    screen at any width; no monitor thread; a terminal of unknown width counts as
    ``UNKNOWN_COLUMNS`` (tqdm keeps one column free, so the cursor never wraps)."""

    monitor_interval = 0            # no TMonitor thread: the caller draws every update

    @staticmethod
    def status_printer(file):
        def print_status(s):
            file.write(_ERASE + s)
            file.flush()
        return print_status

    def display(self, msg=None, pos=None):
        """Draw ``msg`` (default: the formatted bar) or, for ``msg == ""`` (tqdm's erase on close
        with leave=False), erase the line; always line 0, so tqdm's nesting and its terminal-height
        checks (a fresh pseudo-terminal reports no rows) do not apply. Returns whether it drew, so
        that close() writes no '\r' after the erase."""
        self.sp(self.__str__() if msg is None else msg)
        return msg != ""

    @property
    def format_dict(self):
        d = super().format_dict                 # ncols: tqdm's width less one column, -1 (0 columns) or None
        cols = d.get("ncols") or 0
        d["ncols"] = max(cols if cols > 0 else UNKNOWN_COLUMNS - 1, 10)
        return d


# tqdm's default lock also creates a multiprocessing RLock (which fixes this process's start
# method); a thread lock is all one synchronous line needs
_Line.set_lock(threading.RLock())


class StatusLine:
    """A progress callback for ``verb`` that keeps one line on a terminal (see the module doc);
    ``StatusLine(verb, None)`` is a no-op callback. ``file`` is a text file (or a descriptor,
    opened here and closed by :meth:`close`) on the terminal."""

    def __init__(self, verb: str, file):
        if isinstance(file, int):
            file = os.fdopen(file, "w", encoding="utf-8", errors="replace")
        self.verb, self.file = verb, file
        self.t0 = time.perf_counter()
        self.last = 0.0
        self.bar: _Line | None = None
        self.shown = False
        self.state: dict = {}

    @classmethod
    def for_stderr(cls, verb: str, enabled: bool) -> "StatusLine":
        """A status line on a private copy of descriptor 2 if ``enabled`` and :func:`wanted`."""
        if not (enabled and wanted(2)):
            return cls(verb, None)
        try:
            return cls(verb, os.dup(2))
        except OSError:
            return cls(verb, None)

    @property
    def active(self) -> bool:
        return self.file is not None

    @property
    def fd(self) -> int | None:
        """The descriptor the line is drawn on (None once closed, or when inactive)."""
        return None if self.file is None else self.file.fileno()

    def __call__(self, event: dict) -> None:
        if self.file is None:
            return
        kind = event.get("stage")
        key = (kind, event.get("step"), event.get("level"), event.get("candidate"), event.get("done"))
        new_stage = key != self.state.get("_last")          # a new stage, step or finished task is always shown
        s = self.state
        s["_last"] = key
        if kind == "newton":
            s["newton"] = event
        elif kind == "tasks":                       # independent tasks (sweep cases, law patches, targets)
            s["tasks"] = event
        elif kind == "outer":                       # an outer iteration of design --refine
            s.update(outer=event, newton=None)
        elif kind == "release":
            s.update(release=event, newton=None)
        elif kind == "level":
            s.update(phase="solving", level=event, newton=None, release=None)
        elif kind == "design":
            s.update(phase=f"{event['step']} ({event['index']}/{event['steps']})", context=event.get("candidate"))
        elif kind in ("verify", "refine"):           # a stage that runs simulations of its own
            s.update(context={"verify": "verify", "refine": "refine"}[kind], phase=None, level=None, newton=None,
                     release=None, outer=None)
        elif kind == "mesh":
            s.update(phase="meshing", level=None, newton=None, release=None)
        elif kind == "write":
            s.update(context=None, phase="writing files")
        else:
            s.update(phase=str(kind))
        now = time.perf_counter()
        if not new_stage and now - self.last < MIN_INTERVAL_S:
            return
        self.last = now
        self._draw(now)

    def text(self, now: float | None = None) -> str:
        """The line for the current state, e.g. ``design 12 s: verify, level 2/3 (1200 vertices),
        Newton 14: E 1.2345e+01 N mm, |g| 3.1e-04``; with task counts, the part before them
        (``sweep 12 s: ``, to which tqdm adds ``3/6 cases, 00:08 left, last #2 ok (1.0 s)``)."""
        s = self.state
        phase = s.get("phase")
        if phase == "solving" and (s.get("newton") or (s.get("level") and s["level"]["levels"] > 1)):
            phase = None                        # the level and Newton counts say it
        parts = [p for p in (s.get("context"), phase) if p]
        if s.get("level") and s["level"]["levels"] > 1:
            lv = s["level"]
            parts.append(f"level {lv['level']}/{lv['levels']} ({lv['n_vertices']} vertices)")
        if s.get("outer"):
            o = s["outer"]
            parts.append(f"outer iteration {o['iteration']}" + (f" from the {o['start']}" if o.get("start") else "")
                         + f" (rms {o['rms_mm']:.3f} mm)")
        if s.get("release"):
            parts.append(f"release step {s['release']['step']}/{s['release']['steps']}")
        if s.get("newton"):
            n = s["newton"]
            parts.append(f"Newton {n['iteration']}: E {n['energy']:.4e} N mm, |g| {n['gradient_norm']:.1e}")
        elapsed = (time.perf_counter() if now is None else now) - self.t0
        line = f"{self.verb} {elapsed:.0f} s: " + ", ".join(parts)
        return line + ("; " if parts and s.get("tasks") else "")

    def _draw(self, now: float) -> None:
        """Hand the current state to the tqdm bar (made at the first event) and draw it."""
        tasks = self.state.get("tasks")
        fmt = _TASKS if tasks else _EVENTS
        desc = self.text(now)
        postfix = f"last {tasks['last']}" if tasks and tasks.get("last") else ""
        try:
            if self.bar is None:                # tqdm draws it once made
                self.bar = _Line(file=self.file, leave=False, dynamic_ncols=True, position=0, mininterval=0,
                                 smoothing=0, bar_format=fmt, desc=desc, postfix=postfix or None,
                                 unit=(tasks or {}).get("unit", "tasks"), total=(tasks or {}).get("total"),
                                 initial=(tasks or {}).get("done", 0))
            else:
                bar = self.bar
                bar.bar_format = fmt
                if tasks and bar.total is None:     # the first count: the time left is timed from here
                    bar.initial, bar.start_t = tasks["done"], bar._time()
                if tasks:
                    bar.total, bar.unit, bar.n = tasks["total"], tasks.get("unit", "tasks"), tasks["done"]
                bar.set_postfix_str(postfix, refresh=False)
                bar.set_description_str(desc, refresh=False)
                bar.refresh()
            self.shown = True
        except OSError:
            self.close()

    def print_above(self, text: str, file=None) -> None:
        """Print ``text`` (one line, to ``file``, default stdout) above the status line: erase
        it, print, draw it again, so that lines printed during the run are not interleaved."""
        showing = self.shown
        self.clear()
        print(text, file=file or sys.stdout, flush=True)
        if showing and self.bar is not None:
            try:
                self.bar.refresh()
                self.shown = True
            except OSError:
                self.close()

    def clear(self) -> None:
        """Erase the line (before the verb prints its result or error)."""
        if self.bar is not None and self.shown:
            try:
                self.bar.display(msg="")
            except OSError:
                pass
            self.shown = False

    def close(self) -> None:
        """Erase the line and release the descriptor (idempotent)."""
        if self.bar is not None:
            bar, self.bar = self.bar, None
            if not self.shown:
                bar.disable = True                  # nothing on screen: tqdm's close need not erase
            try:
                bar.close()                         # leave=False: erases the line
            except OSError:
                pass
            self.shown = False
        if self.file is not None:
            try:
                self.file.close()
            except OSError:
                pass
            self.file = None
