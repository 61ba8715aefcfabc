"""The command line's progress indicator: redrawn in place with the time left on a terminal; plain
lines without carriage returns in logs and pipes."""

import contextlib
import io

from jaxpbr.cli._common import Progress


def _run(tty: bool, total: int = 10) -> str:
    buf = io.StringIO()
    with contextlib.redirect_stderr(buf):
        p = Progress("bake", tty=tty)
        for i in range(total + 1):
            p(i, total)
    return buf.getvalue()


def test_logs_get_plain_lines_per_quarter():
    out = _run(tty=False)
    assert "\r" not in out
    lines = out.splitlines()
    assert [line.split()[1] for line in lines] == ["0/10", "3/10", "5/10", "8/10", "10/10"]
    assert "left" in lines[1] and "left" not in lines[-1]


def test_a_terminal_gets_one_line_redrawn_with_the_time_left():
    out = _run(tty=True, total=4)
    assert out.count("\r") == 5 and out.endswith("\n") and out.count("\n") == 1
    assert "s left" in out.split("\r")[2]


def test_quiet_prints_nothing():
    buf = io.StringIO()
    with contextlib.redirect_stderr(buf):
        p = Progress("bake", quiet=True)
        p(1, 2)
    assert buf.getvalue() == ""
