"""The status line of the long verbs (simulate, design) on a terminal's stderr.

The lower layers report progress through a callback (forward.simulate, inverse.design:
dicts such as {"stage": "newton", "iteration": 12, "energy": ..., "gradient_norm": ...});
:class:`StatusLine` turns them into one line that is rewritten in place (carriage return and
erase-line) and erased again before the verb prints its result or error, so a terminal ends
with the same lines as a pipe. It is shown only when stderr is a terminal, not under CI
(the ``CI`` variable), not with TERM=dumb and not with ``--quiet`` or ``-v`` (whose
per-iteration lines go to stdout instead); in a pipe nothing of it is written.

It writes to its own copy of file descriptor 2 taken before the verb runs, because the CLI
redirects descriptor 2 while a verb runs to keep library chatter from the terminal. Updates
are synchronous (no thread), at most ``MIN_INTERVAL_S`` apart unless the stage changes.
"""
from __future__ import annotations

import os
import time

MIN_INTERVAL_S = 0.1
_ERASE = "\r\x1b[2K"


def wanted(fd: int = 2, *, quiet: bool = False, env=None) -> bool:
    """Whether a status line belongs on ``fd``: a terminal, not quiet, not CI, not TERM=dumb."""
    env = os.environ if env is None else env
    if quiet or env.get("CI", "").strip().lower() not in ("", "0", "false", "no") or env.get("TERM") == "dumb":
        return False
    try:
        return os.isatty(fd)
    except OSError:
        return False


class StatusLine:
    """A progress callback for ``verb`` that keeps one line on a terminal (see the module doc);
    ``StatusLine(verb, None)`` is a no-op callback."""

    def __init__(self, verb: str, fd: int | None):
        self.verb, self.fd = verb, fd
        self.t0 = time.perf_counter()
        self.last = 0.0
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
        return self.fd is not None

    def __call__(self, event: dict) -> None:
        if self.fd is None:
            return
        kind = event.get("stage")
        key = (kind, event.get("step"), event.get("level"), event.get("candidate"))
        new_stage = key != self.state.get("_last")          # a new stage or step is always shown
        s = self.state
        s["_last"] = key
        if kind == "newton":
            s["newton"] = event
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
        self._write(self.text(now))

    def text(self, now: float | None = None) -> str:
        """The line for the current state, e.g. ``design 12 s: verify, level 2/3 (1200 vertices),
        Newton 14: E 1.2345e+01 N mm, |g| 3.1e-04``."""
        s = self.state
        phase = s.get("phase")
        if phase == "solving" and (s.get("newton") or (s.get("level") and s["level"]["levels"] > 1)):
            phase = None                        # the level and Newton counts say it
        parts = [p for p in (s.get("context"), phase) if p]
        if s.get("level") and s["level"]["levels"] > 1:
            lv = s["level"]
            parts.append(f"level {lv['level']}/{lv['levels']} ({lv['n_vertices']} vertices)")
        if s.get("outer"):
            parts.append(f"outer iteration {s['outer']['iteration']} (rms {s['outer']['rms_mm']:.3f} mm)")
        if s.get("release"):
            parts.append(f"release step {s['release']['step']}/{s['release']['steps']}")
        if s.get("newton"):
            n = s["newton"]
            parts.append(f"Newton {n['iteration']}: E {n['energy']:.4e} N mm, |g| {n['gradient_norm']:.1e}")
        elapsed = (time.perf_counter() if now is None else now) - self.t0
        return f"{self.verb} {elapsed:.0f} s: " + ", ".join(parts)

    def _write(self, text: str) -> None:
        try:
            width = os.get_terminal_size(self.fd).columns or 100      # 0: a terminal of unknown size
        except OSError:
            width = 100
        try:
            os.write(self.fd, (_ERASE + text[: max(width - 1, 10)]).encode("utf-8", "replace"))
            self.shown = True
        except OSError:
            self.close()

    def clear(self) -> None:
        """Erase the line (before the verb prints its result or error)."""
        if self.fd is not None and self.shown:
            try:
                os.write(self.fd, _ERASE.encode())
            except OSError:
                pass
            self.shown = False

    def close(self) -> None:
        """Erase the line and release the descriptor (idempotent)."""
        self.clear()
        if self.fd is not None:
            try:
                os.close(self.fd)
            except OSError:
                pass
            self.fd = None
