"""`hilcal --help` starts fast: the help of the app and of its commands loads none of the heavy libraries.

Guarded by tracing imports (which top-level packages are in ``sys.modules`` once the help is printed), not by a
timer, so a loaded CI machine cannot make it flaky; benchmarks/bench_startup.py measures the seconds.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("numpy", "matplotlib", "scipy", "starlette", "uvicorn", "sqlalchemy", "alembic", "psycopg", "cantools",
         "pymodbus", "can", "serial", "selenium", "pypdf", "weasyprint")
"""Each costs tens to hundreds of milliseconds to import; the commands that need one import it themselves."""

_TRACE = """
import json, runpy, sys
sys.argv = ["hilcal", *sys.argv[1:]]
try:
    runpy.run_module("procedures.cli", run_name="__main__", alter_sys=True)
except SystemExit as e:
    code = e.code
else:
    code = 0
print(json.dumps({"code": code, "modules": sorted({m.split(".")[0] for m in sys.modules})}), file=sys.stderr)
"""


def _loaded(*args: str) -> tuple[int, str, set[str]]:
    """Run `python -m procedures.cli ARGS` in a fresh interpreter: exit code, stdout and the top-level packages."""
    done = subprocess.run([sys.executable, "-c", _TRACE, *args], capture_output=True, text=True, timeout=60,
                          check=False)
    report = json.loads(done.stderr.strip().splitlines()[-1])
    return report["code"] or 0, done.stdout, set(report["modules"])


@pytest.mark.parametrize("args", [["--help"], ["history", "--help"], ["identify", "--help"], ["run", "--help"],
                                  ["records", "sync", "--help"]])
def test_help_loads_no_heavy_library(args):
    code, stdout, modules = _loaded(*args)
    assert code == 0 and "Usage" in stdout
    assert not modules & set(HEAVY), f"`hilcal {' '.join(args)}` imported {sorted(modules & set(HEAVY))}"


def test_trace_sees_what_a_command_imports(tmp_path):
    """The control: a command that does work (here failing on a missing recording) loads numpy and scipy."""
    code, _, modules = _loaded("identify", str(tmp_path / "missing.csv"))
    assert code == 2
    assert {"numpy", "scipy", "structlog"} <= modules


def test_module_entry_point_exists():
    """Benchmarks and the tests start the command line as `python -m procedures.cli`."""
    done = subprocess.run([sys.executable, "-m", "procedures.cli", "--help"], capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode == 0 and "identify" in done.stdout


def test_a_run_loads_no_plotting_or_statistics_before_the_machine_moves():
    """`hilcal run` (and its resume after a SIGKILL) reaches the devices without matplotlib or scipy.stats: they
    are loaded for the report, after the measurements. The lazy packages (hilcal.reports, hilcal.discovery) make
    this possible; a top-level import of either would bring the half second back to every start."""
    code = ("import json, sys\nimport procedures.runner, procedures.cli.sim_station, procedures.cli.operator\n"
            "print(json.dumps(sorted(sys.modules)))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    modules = set(json.loads(done.stdout))
    assert "procedures.engine" in modules and "drivers.controller.hilcal_can" in modules  # the control: it did load
    assert not {m for m in modules if m == "matplotlib" or m.startswith(("scipy.stats", "matplotlib."))}


def test_lazy_packages_name_what_their_modules_hold():
    """Every name a lazy package exports resolves to the object of the module it names."""
    import hilcal.discovery
    import hilcal.reports

    for package in (hilcal.discovery, hilcal.reports):
        for name in package.__all__:
            value = getattr(package, name)
            assert value.__module__.startswith(package.__name__ + "."), (package.__name__, name)
