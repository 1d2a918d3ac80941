"""What the sign-off tests share: the operator, the station with limits the machine cannot meet, the command
runner and the PDF's text."""

from __future__ import annotations

import subprocess
import unicodedata
from pathlib import Path

from pypdf import PdfReader

from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import instant_timing

OPERATOR = "A. Tester"
REPEATABILITY_MM = 0.02
STATION = f"""
name = "test bay"
[machine]
serial = "SIM-0001"
[cmm]
identity = "simulated CMM, serial 1"
stated_uncertainty_mm = 0.002
calibration_due = 2020-01-31
[acceptance]
max_position_mm = 0.5
ap_position_mm = 0.5
rp_position_mm = 0.02
{instant_timing()}"""



def hilcal(*args: str, records: Path) -> subprocess.CompletedProcess[str]:
    """The command in this process (tests/cli/in_process.py), with its own records file and a wide terminal."""
    return hilcal_in_process(*args, env={"HILCAL_RECORDS": str(records), "COLUMNS": "200"})


def pdf_text(path: Path) -> str:
    """The PDF's text with ligatures (ﬁ) undone."""
    return unicodedata.normalize("NFKC", "\n".join(page.extract_text() for page in PdfReader(path).pages))


