"""`hilcal COMMAND ...` in the test's own process, for tests whose claims are about what a command did, not about its
being a process of its own (a kill, two runs at once, a terminal, the installed entry point: those tests start one).

A new `hilcal run` process spends about 2 CPU s importing numpy, scipy, matplotlib and SQLAlchemy (see `python -X
importtime -m procedures.cli run --help`), which a test worker has already imported. The command runs as typed (typer's
CliRunner: the same app, arguments, environment and standard input); a `--sim` run still starts its simulator as a
process of its own and talks to it over real transports. The answer has the fields of subprocess.run's, so a test can
switch between the two.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import traceback
from collections.abc import Mapping
from pathlib import Path

from typer.testing import CliRunner

from procedures.cli.app import app


def hilcal_in_process(*args: str, env: Mapping[str, str] | None = None, input: str | None = None,
                      cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """Run `hilcal *args` here; returncode, stdout and stderr as a process would have them (an exception that
    escapes the command: its traceback in stderr and return code 1, as Python's own exit)."""
    with contextlib.chdir(cwd or os.getcwd()):
        result = CliRunner().invoke(app, list(args), env=dict(env or {}), input=input)
    stderr = result.stderr
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        stderr += "".join(traceback.format_exception(*result.exc_info))
    return subprocess.CompletedProcess(["hilcal", *args], result.exit_code, result.stdout, stderr)
