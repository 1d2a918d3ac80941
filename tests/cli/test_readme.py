"""The README's commands run as written: every `hilcal` line of its shell blocks and the simplest form of every command
of its command table parses; each command's `--help` prints; and the quick start, `hilcal run --sim --yes`, runs (with
an instant simulator and a small plan added, as tests/cli/sim_speed.py explains) into the run folder it prints.

The newcomer's path of the README (geometry file, robot file, simulated run, pre-flight check) runs in
tests/cli/test_newcomer.py.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import typer
from typer.core import TyperGroup
from typer.testing import CliRunner

from procedures.cli.app import app
from tests.cli.sim_speed import INSTANT_SIM

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
SHELL_BLOCK = re.compile(r"```sh\n(.*?)```", re.S)
OPTIONAL = re.compile(r"\[[^\[\]]*\]")
NUMBERS = {"N": "2", "M": "30", "T": "0.03", "S": "0.005", "A": "0.01", "P": "8766"}
"""The README's placeholders for numbers, and a number each stands for (the others stand for names and paths)."""


def shell_commands(text: str = README) -> list[str]:
    """The `hilcal` lines of the README's ```sh blocks, comments removed."""
    lines = [line.split(" #")[0].strip() for block in SHELL_BLOCK.findall(text) for line in block.splitlines()]
    return [line for line in lines if line.startswith("hilcal ")]


def table_commands(text: str = README) -> list[str]:
    """The command table's first column, each alternative in its simplest form (optional [parts] and ... left out)."""
    section = text.split("## Command line", 1)[1].split("\n## ", 1)[0]
    found = []
    for row in section.splitlines():
        if not row.startswith("| `hilcal"):
            continue
        cell = re.split(r"(?<!\\)\|", row)[1].replace("`", "").replace("\\|", "|")
        for alternative in cell.split(" / "):
            words = OPTIONAL.sub("", OPTIONAL.sub("", alternative)).split()
            words = [w.removesuffix("...") for w in words if w != "..."]
            if words and words[0] == "hilcal":
                found.append(" ".join(words))
    return found


def parse(args: list[str]) -> tuple[str, dict]:
    """The command's name and its parsed parameters, as `hilcal ARGS` would parse them (click's UsageError if not)."""
    command = typer.main.get_command(app)
    ctx = command.make_context("hilcal", list(args))
    while isinstance(command, TyperGroup):
        name, command, rest = command.resolve_command(ctx, [*ctx._protected_args, *ctx.args])  # click's own split
        ctx = command.make_context(name, rest, parent=ctx)
    return command.name, ctx.params


def test_the_readme_is_read_as_intended() -> None:
    """The control: the quick start, the newcomer's lines and every table row are found."""
    shell, table = shell_commands(), table_commands()
    assert "hilcal run --sim --yes" in shell and "hilcal run --sim --yes --robot robot.toml" in shell
    assert "hilcal robot-from-geometry geometry.toml --out robot.toml" in shell
    assert {"hilcal run --sim --yes", "hilcal run --station FILE", "hilcal run --resume RUN_ID",
            "hilcal check --station FILE", "hilcal records sync FOLDER"} <= set(table)
    assert len(table) >= 20
    assert table_commands("## Command line\n| `hilcal sim [--json]` / `--x` | y |\n") == ["hilcal sim"]


@pytest.mark.parametrize("line", sorted(set(shell_commands() + table_commands())))
def test_every_readme_command_parses(line: str) -> None:
    name, params = parse([NUMBERS.get(word, word) for word in shlex.split(line)[1:]])
    assert name in line and isinstance(params, dict)


def test_every_readme_command_prints_its_help() -> None:
    runner = CliRunner()
    for path in sorted({tuple(w for w in shlex.split(line)[1:3] if not w.startswith("-") and w.islower())[:2]
                        for line in shell_commands() + table_commands()}):
        path = path[:2] if path[:1] == ("records",) else path[:1]
        result = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "80"})
        assert result.exit_code == 0 and "Usage: " in result.output, (path, result.output)


@pytest.fixture(scope="module")
def quick_start(tmp_path_factory: pytest.TempPathFactory, small_plan: Path) -> tuple[Path, str, int]:
    """`hilcal run --sim --yes` as the quick start writes it, in an empty folder (the instant simulator and a small plan
    added for speed: neither changes what the command does)."""
    work = tmp_path_factory.mktemp("quick_start")
    (work / "instant.toml").write_text(INSTANT_SIM)
    line = shell_commands()[shell_commands().index("hilcal run --sim --yes")]
    env = {**os.environ, "HILCAL_RECORDS": str(work / "records.sqlite"), "COLUMNS": "200",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}  # runs from another folder
    done = subprocess.run([sys.executable, "-m", "procedures.cli", *shlex.split(line)[1:], "--sim-config",
                           str(work / "instant.toml"), "--plan", str(small_plan)], cwd=work, env=env,
                          capture_output=True, text=True, timeout=240, check=False)
    return work, done.stdout + done.stderr, done.returncode


@pytest.mark.slow
def test_the_quick_start_runs_into_the_folder_it_prints(quick_start: tuple[Path, str, int]) -> None:
    work, output, code = quick_start
    assert code == 0, output
    run_id = re.search(r"^run (\S+): its folder is runs/(\S+)$", output, re.M)
    assert run_id is not None and run_id.group(1) == run_id.group(2), output
    folder = work / "runs" / run_id.group(1)
    report = json.loads((folder / "report.json").read_text())
    assert report["run_id"] == run_id.group(1) and report["status"] == "complete"
    assert (folder / "report.html").is_file() and (folder / "certificate.html").is_file()
    assert f"report       runs/{run_id.group(1)}/report.html" in output


@pytest.mark.slow
def test_the_quick_start_says_what_it_simulated(quick_start: tuple[Path, str, int]) -> None:
    work, output, _ = quick_start
    said = " ".join(output.split())
    for words in ("simulated machine: robot paper-table1 (the built-in paper Table 1 robot)",
                  "geometric errors: the paper's Table 2", "beyond the geometry: nothing",
                  "instrument: the simulated CMM (I++ DME), noise 0.002 mm per touch-point coordinate",
                  "timing: the simulated station's own"):
        assert words in said
    report = json.loads(next((work / "runs").glob("*/report.json")).read_text())
    simulation = report["simulation"]
    assert simulation["errors"]["source"] == "table2" and simulation["time_scale"] == 100000.0
    assert 0.9 < simulation["errors"]["max_joint_error_mm"] < 1.0  # Table 2's largest joint error is 0.98 mm
    assert simulation["timing"].startswith("the simulated station's own")
    assert "of the simulated machine's time" in report["environment"]["note"]
