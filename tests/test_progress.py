"""Progress of the long verbs (selfshape.progress): a status line on a terminal's stderr (levels,
Newton iterations with energy and gradient norm), erased before the result or error line;
nothing in a pipe, under CI or with --quiet. The lower layers report through callbacks."""
import os
import pty
import re
import select
import subprocess
import sys

import numpy as np
import pytest

from selfshape.progress import StatusLine, wanted

ROOT = os.path.join(os.path.dirname(__file__), "..")
EXAMPLE = os.path.join(ROOT, "examples", "strip_narrow.toml")
ERASE = b"\r\x1b[2K"


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "TERM")}
    env.update(PYTHONPATH=os.path.abspath(ROOT), MPLBACKEND="Agg", TERM="xterm", **extra)
    return env


def _run_on_pty(argv_code, env):
    """Run ``python -c argv_code`` with stderr on a pseudo-terminal and stdout in a pipe:
    (exit status, stdout bytes, the bytes the terminal received)."""
    master, slave = pty.openpty()
    p = subprocess.Popen([sys.executable, "-c", argv_code], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                         stderr=slave, env=env, cwd=ROOT)
    os.close(slave)
    got = b""
    while True:
        r, _, _ = select.select([master], [], [], 0.2)
        if r:
            try:
                chunk = os.read(master, 65536)
            except OSError:          # EIO: the child closed the terminal
                chunk = b""
            if not chunk:
                break
            got += chunk
        elif p.poll() is not None:
            break
    out = p.stdout.read()
    rc = p.wait(timeout=300)
    os.close(master)
    return rc, out, got


def _visible(term: bytes) -> list:
    """The lines a terminal shows at the end: each erase-line wipes the status line."""
    text = term.replace(b"\r\n", b"\n").decode()
    lines = [re.split(r"\r\x1b\[2K", line)[-1] for line in text.split("\n")]
    return [x for x in lines if x]


SIM = (f"import sys; from selfshape.cli import main; "
       f"sys.exit(main(['simulate', {EXAMPLE!r}, '-o', sys.argv[1] if len(sys.argv) > 1 else 'OUT', "
       f"'--size', '3', '--no-png'] + EXTRA))")


def _sim_code(out, extra=()):
    return SIM.replace("'OUT'", repr(str(out))).replace("EXTRA", repr(list(extra)))


def test_status_line_shows_on_a_terminal_and_is_erased(tmp_path):
    rc, out, term = _run_on_pty(_sim_code(tmp_path / "o"), _env())
    assert rc == 0, (out, term)
    assert b"Newton" in term and b"|g|" in term and b"simulate " in term and ERASE in term
    assert term.endswith(ERASE), "the status line is erased before the verb ends"
    assert _visible(term) == []                 # nothing left on stderr once erased
    assert len(out.decode().splitlines()) == 1 and out.startswith(b"converged")


@pytest.mark.parametrize("how", ["pipe", "quiet", "ci"])
def test_no_progress_in_a_pipe_under_ci_or_quiet(tmp_path, how):
    if how == "pipe":
        p = subprocess.run([sys.executable, "-c", _sim_code(tmp_path / "o")], capture_output=True, env=_env(),
                           cwd=ROOT, timeout=300)
        assert p.returncode == 0 and p.stderr == b""
        return
    extra = ["--quiet"] if how == "quiet" else []
    env = _env(CI="true") if how == "ci" else _env()
    rc, out, term = _run_on_pty(_sim_code(tmp_path / "o", extra), env)
    assert rc == 0 and term == b"", term


def test_an_error_after_progress_is_one_line_on_the_terminal(tmp_path):
    """The status line was showing when the error came: erased, then the one error line."""
    code = ("import sys, forward.simulate as fs\n"
            "from shellfem.errors import SelfshapeError\n"
            "def boom(*a, **k):\n    raise SelfshapeError('boom.dxf: cannot write')\n"
            "fs.write_cad = boom\n" + _sim_code(tmp_path / "o").replace("; ", "\n"))
    rc, out, term = _run_on_pty(code, _env())
    assert rc == 2 and b"Newton" in term
    assert _visible(term) == ["selfshape simulate: error: boom.dxf: cannot write"]
    assert out == b""


def test_design_shows_its_stages_on_a_terminal(tmp_path):
    from geometry.target import cylinder_patch
    V, F = cylinder_patch(n_arc=16, n_len=12)
    target = tmp_path / "cyl.obj"
    with open(target, "w") as f:
        f.writelines(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V)
        f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F)
    code = (f"import sys; from selfshape.cli import main; "
            f"sys.exit(main(['design', {str(target)!r}, '-o', {str(tmp_path / 'd')!r}, '--diagonal', '60', '--stretch', '1.6']))")
    rc, out, term = _run_on_pty(code, _env())
    assert rc == 0, term
    shown = term.decode()
    for step in ("load and refine (1/6)", "flattening (4/6)", "ribbon layout (5/6)", "writing files"):
        assert f": {step}" in shown, (step, shown[-500:])
    assert _visible(term) == [] and out.decode().startswith("design written to")


def test_wanted_and_the_line_text():
    r, w = os.pipe()
    try:
        assert not wanted(w, env={})                         # a pipe
        master, slave = pty.openpty()
        try:
            assert wanted(slave, env={"TERM": "xterm"})
            assert not wanted(slave, env={"CI": "true"}) and not wanted(slave, env={"TERM": "dumb"})
            assert not wanted(slave, quiet=True, env={})
            assert wanted(slave, env={"CI": "false"})
        finally:
            os.close(master)
            os.close(slave)
        line = StatusLine("design", w)
        for e in ({"stage": "design", "step": "flattening", "index": 4, "steps": 6},
                  {"stage": "verify"}, {"stage": "level", "level": 1, "levels": 2, "n_vertices": 120},
                  {"stage": "newton", "iteration": 3, "energy": 12.5, "gradient_norm": 3e-4},
                  {"stage": "refine"}, {"stage": "outer", "iteration": 2, "rms_mm": 0.4321},
                  {"stage": "outer", "iteration": 1, "start": "released state", "rms_mm": 1.5}):
            line(e)
            line.last = 0.0                                  # no throttling in the test
        line.close()
        got = os.read(r, 65536).decode()
        assert "design 0 s: flattening (4/6)" in got
        assert "design 0 s: verify, level 1/2 (120 vertices), Newton 3: E 1.2500e+01 N mm, |g| 3.0e-04" in got
        assert "design 0 s: refine, outer iteration 2 (rms 0.432 mm)" in got
        assert "design 0 s: refine, outer iteration 1 from the released state (rms 1.500 mm)" in got
        assert got.endswith("\r\x1b[2K")
        assert line.fd is None
        StatusLine("x", None)({"stage": "newton"})           # inactive: a no-op
    finally:
        os.close(r)


def test_newton_calls_back_per_accepted_step():
    from shellfem.model import ShellModel
    from shellfem.newton import newton
    from shellfem.sheet import Sheet
    M = ShellModel.homogeneous(Sheet.rectangle(4, 2, 4, 2), 1.0, 0.3, 0.1)
    q = M.initial_state()
    q[2:3 * M.n_vertices:3] += 0.05 * np.sin(np.arange(M.n_vertices))
    free = np.ones(M.n_dofs, bool)
    free[:6] = False
    seen = []
    r = newton(M, q, free, callback=seen.append, max_iterations=20)
    assert len(seen) == len(r.history) - (1 if r.converged else 0)
    assert all({"iteration", "energy", "gradient_norm"} <= set(h) for h in seen)


# ----------------------------------------------------------------------------- counted tasks (tqdm)
def _drain(master) -> bytes:
    got = b""
    while select.select([master], [], [], 0.05)[0]:
        got += os.read(master, 65536)
    return got


def test_task_counts_show_done_total_and_time_left_without_a_thread(tmp_path):
    """Sweeps and the law's patches: done / total and tqdm's time left, timed from the first count
    (tasks already done then are not speed); no thread is started; erased on close."""
    import threading
    import time

    from selfshape.progress import _Line
    master, slave = pty.openpty()
    try:
        threads = threading.active_count()
        line = StatusLine("sweep", os.dup(slave))
        line({"stage": "tasks", "done": 2, "total": 6, "unit": "cases"})           # 2 reused
        assert threading.active_count() == threads and _Line.monitor is None
        first = _drain(master).decode()
        assert first == "\r\x1b[2Ksweep 0 s: 2/6 cases, ? left"
        time.sleep(0.5)
        line({"stage": "tasks", "done": 3, "total": 6, "unit": "cases", "last": "#4 ok"})
        shown = _drain(master).decode().split("\r\x1b[2K")[-1]
        m = re.fullmatch(r"sweep 1 s: 3/6 cases, 00:0(\d) left, last #4 ok", shown)
        assert m and 1 <= int(m.group(1)) <= 2, shown         # 1 case in ~0.5 s: 3 more in ~1.5 s
        line.print_above("case 3/6 #4 ok", file=open(os.dup(slave), "w"))
        above = _drain(master).decode()
        assert above.startswith("\r\x1b[2Kcase 3/6 #4 ok") and above.endswith(shown)
        line.close()
        assert _drain(master) == ERASE and line.fd is None and threading.active_count() == threads
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("columns", [0, 40])
def test_the_line_fits_the_terminal(columns):
    """tqdm trims the line to the terminal's width less one column; a terminal of unknown size
    (0 columns, a fresh pseudo-terminal) counts as 100."""
    import fcntl
    import struct
    import termios
    master, slave = pty.openpty()
    try:
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
        line = StatusLine("design", os.dup(slave))
        line({"stage": "design", "step": "x" * 200, "index": 1, "steps": 6})
        shown = _drain(master).decode().split("\r\x1b[2K")[-1]
        assert len(shown) == (columns or 100) - 1 and shown.startswith("design 0 s: ")
        line.close()
    finally:
        os.close(master)
        os.close(slave)


def test_law_generation_reports_patches_done(tmp_path, monkeypatch):
    """validation.law_tables.main counts the simulated patches (the grid and the mirror's check
    row) through the status factory; --quiet asks for no line."""
    from validation import law_tables

    def fake_row(call):              # a cheap stand-in for one patch simulation (kappa in 1/mm)
        return {"thickness_mm": call["thickness"], "spacing_mm": call["spacing"], "side": call["side"],
                "kappa_per_mm": 0.01 * call["thickness"] / call["spacing"], "converged": True, "reason": "ok",
                "newton_iterations": 1, "n_triangles": 1, "time_s": 0.0}
    monkeypatch.setattr(law_tables, "simulate_row_task", fake_row)
    events, asked = [], []

    class Sink:
        closed = False

        def __call__(self, e):
            events.append(e)

        def close(self):
            Sink.closed = True

    def status(enabled):
        asked.append(enabled)
        return Sink()
    args = ["--model", "sim", "--thickness", "0.3", "0.4", "--spacing", "3.9", "6.5", "--back", "mirror",
            "--out", str(tmp_path / "law.csv")]
    assert law_tables.main(args, status=status) == 0
    assert asked == [True] and Sink.closed
    assert [(e["done"], e["total"], e["unit"]) for e in events] == [(k, 5, "patches") for k in range(6)]
    assert events[-1]["last"].endswith(" back") and events[1]["last"] == "t 0.3 mu2 3.9 front"
    law_tables.main(args + ["-q"], status=status)
    assert asked[-1] is False


def test_sweep_shows_cases_done_and_time_left(tmp_path):
    """`selfshape sweep` (serial, 6 strips of about a second): the status line counts the cases
    with the time left and is erased; stdout keeps its line per case and the summary line."""
    sweep = os.path.join(ROOT, "examples", "sweep_strip.toml")
    code = (f"import sys; from selfshape.cli import main; "
            f"sys.exit(main(['sweep', {sweep!r}, '-o', {str(tmp_path / 's')!r}, '--workers', '0']))")
    rc, out, term = _run_on_pty(code, _env())
    assert rc == 0, term
    shown = term.decode()
    assert re.search(r"sweep \d+ s: 0/6 cases, \? left", shown), shown[:400]
    assert re.search(r"sweep \d+ s: 5/6 cases, \d\d:\d\d left, last #4 ok", shown), shown[-400:]
    assert _visible(term) == []
    lines = out.decode().splitlines()
    assert [x.split()[1] for x in lines[:6]] == [f"{k}/6" for k in range(1, 7)] and lines[6].startswith("6 cases")
