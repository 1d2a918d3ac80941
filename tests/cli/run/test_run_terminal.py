"""`hilcal run --sim` without --yes at a terminal: every question stands readable on the screen while the run waits.

The run is driven in a pseudo-terminal whose screen a terminal emulator (pyte) keeps, as the operator's terminal
would. Each question is read from that screen, not from the bytes the run wrote, and is answered only once it has
stood there, whole and under the cursor, while the progress bar would have redrawn itself several times: a bar that
draws over the question fails this. The upload question must have the approval's findings on the screen above it.
A Ctrl-C mid-measurement pauses the run and its question is read the same way; the run then goes on and completes.
"""

from __future__ import annotations

import fcntl
import os
import pty
import re
import select
import struct
import sys
import termios
import time
from pathlib import Path

import pyte
import pytest

from procedures.journal import Journal

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

ROWS, COLUMNS = 40, 120
SIM = """
[controller]
time_scale = 100000.0
[cmm]
time_scale = 0.0001
[rig.temperature]
drift_k_per_h = 0.0
amplitude_k = 0.0
"""
"""The servo near-instant and the CMM at a fifth of the simulated station's time (about 0.08 s a pose): most of a
measuring pose is spent waiting on a device, so the Ctrl-C lands there, as at a machine, and pauses rather than
aborts."""
STANDS_S = 1.0
"""How long a question must stand unchanged: the bar redraws ten times a second."""
BAR = re.compile(r"(measure|verify) pose (\d+) .* (\d+)/(\d+) \d+:\d\d:\d\d")


class Terminal:
    """A command in a pseudo-terminal of ROWS x COLUMNS, its screen kept by a terminal emulator."""

    def __init__(self, argv: list[str], env: dict[str, str]) -> None:
        self.screen = pyte.Screen(COLUMNS, ROWS)
        self.stream = pyte.ByteStream(self.screen)
        self.pid, self.fd = pty.fork()
        if self.pid == 0:  # the child: the pseudo-terminal is its controlling terminal, stdin, stdout and stderr
            fcntl.ioctl(0, termios.TIOCSWINSZ, struct.pack("HHHH", ROWS, COLUMNS, 0, 0))
            os.execve(argv[0], argv, env)
        self.ended = False

    def lines(self) -> list[str]:
        return [line.rstrip() for line in self.screen.display]

    def text(self) -> str:
        return "\n".join(line for line in self.lines() if line)

    def _read(self, wait_s: float) -> None:
        ready, _, _ = select.select([self.fd], [], [], wait_s)
        if not ready:
            return
        try:
            data = os.read(self.fd, 65536)
        except OSError:  # EIO: the child closed the terminal
            data = b""
        if not data:
            self.ended = True
        self.stream.feed(data)

    def wait_for(self, what: str | re.Pattern[str], timeout_s: float = 120.0) -> str:
        """Read until a screen line holds `what` (a text or a pattern); that line."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self.ended:
            self._read(0.05)
            for line in self.lines():
                if (what in line) if isinstance(what, str) else what.search(line):
                    return line
        raise AssertionError(f"not on the screen: {what!r}; the screen:\n{self.text()}")

    def question(self, text: str) -> list[str]:
        """Wait for the question, let the bar redraw for STANDS_S, check it stands whole under the cursor; the
        screen's lines down to it."""
        self.wait_for(text)
        until = time.monotonic() + STANDS_S
        while time.monotonic() < until and not self.ended:
            self._read(0.05)
        lines = self.lines()
        row = lines[self.screen.cursor.y]
        assert row.startswith(text) and row.endswith("[y/N]:"), f"question drawn over: {row!r}\n{self.text()}"
        assert not any(BAR.search(line) for line in lines), f"the bar is on the screen while asking:\n{self.text()}"
        return lines[:self.screen.cursor.y + 1]

    def send(self, keys: str) -> None:
        os.write(self.fd, keys.encode())

    def exit_code(self, timeout_s: float = 120.0) -> int:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self._read(0.05)
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                while not self.ended:
                    self._read(0.05)
                return os.waitstatus_to_exitcode(status)
        raise AssertionError(f"the run did not end; the screen:\n{self.text()}")

    def close(self) -> None:
        try:
            os.kill(self.pid, 9)
            os.waitpid(self.pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass
        os.close(self.fd)


@pytest.fixture
def terminal(tmp_path: Path, small_plan: Path):
    (tmp_path / "sim.toml").write_text(SIM)
    env = {**os.environ, "HILCAL_RECORDS": str(tmp_path / "records.sqlite"), "TERM": "xterm",
           "COLUMNS": str(COLUMNS), "LINES": str(ROWS)}
    term = Terminal([sys.executable, "-m", "procedures.cli", "run", "--sim", "--sim-config", str(tmp_path / "sim.toml"),
                     "--plan", str(small_plan), "--out", str(tmp_path / "run")], env)
    yield term
    term.close()


def test_every_question_stands_on_the_screen_until_answered(terminal: Terminal, tmp_path: Path) -> None:
    terminal.wait_for("Operator's name (recorded with the run and on the certificate):", timeout_s=60)
    terminal.send("Ada Lovelace\r")
    above = terminal.question("Mount the three platform and three base tooling spheres; CMM homed and aligned?")
    assert any("total" in line for line in above), "the machine-time estimate stays above the first question"
    terminal.send("y\r")
    above = terminal.question("Clear the area around the platform: it is about to move. Go on?")
    assert above[-2].startswith("Mount the three platform") and above[-2].endswith("[y/N]: y")
    terminal.send("y\r")

    measuring = terminal.wait_for(BAR)  # the bar is back below the answers and counts the poses
    assert BAR.search(measuring).group(1) == "measure"
    terminal.send("\x03")
    terminal.question("Paused: motion stopped. Continue the run?")
    terminal.send("y\r")
    terminal.wait_for(BAR)

    above = terminal.question("Upload the full (ls) to the controller?")
    findings = above[above.index("What this run's recording shows beyond the geometry (faults first):"):]
    assert any(line.startswith("verification poses now (measured): max") for line in findings)
    assert any(line.startswith("predicted after the upload: max") for line in findings)
    assert findings[-2].startswith("upload sha256 ")
    terminal.send("y\r")

    code = terminal.exit_code()
    assert code in (0, 4), terminal.text()
    assert re.search(r"run \S+: complete", terminal.text())
    with Journal(tmp_path / "run" / "journal.sqlite") as journal:
        answers = {e["data"]["key"]: e["data"]["answer"] for e in journal.events("prompt")}
        assert answers == {"spheres": True, "area": True, "upload": True}
        assert journal.count_events("resumed_after_pause") == 1
        assert journal.run_info()["options"]["operator"] == "Ada Lovelace"
