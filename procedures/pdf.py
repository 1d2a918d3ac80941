"""Print an HTML page to PDF with headless Chromium (``--print-to-pdf``): the page's own print CSS sets the paper.

Chromium renders exactly what the browser shows, with the page's ``@page`` size and margins, and is already on
every station that runs the operator panel (``.ci/run`` installs it); WeasyPrint would add a second HTML engine
and its system libraries for the same result. Each print gets a fresh, throw-away profile, no network features and
a bounded time. HILCAL_CHROMIUM names the browser if it is not ``chromium`` or ``chromium-browser`` on the PATH.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import structlog

log = structlog.get_logger(__name__)

FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--no-pdf-header-footer")
TIMEOUT_S = 60.0


class PdfError(RuntimeError):
    """No PDF was written (no browser, or the browser failed); the message says why and how to fix it."""


def find_chromium() -> str | None:
    """The headless browser: $HILCAL_CHROMIUM, else chromium or chromium-browser on the PATH."""
    named = os.environ.get("HILCAL_CHROMIUM")
    if named:
        return shutil.which(named) or (named if Path(named).is_file() else None)
    return shutil.which("chromium") or shutil.which("chromium-browser")


def print_to_pdf(html_path: Path, pdf_path: Path, *, timeout_s: float = TIMEOUT_S) -> Path:
    """Write pdf_path from the HTML file (written to a temporary name first, so a failed print leaves no PDF)."""
    browser = find_chromium()
    if browser is None:
        raise PdfError("no headless Chromium found (install it: apt-get install -y chromium, or set HILCAL_CHROMIUM)")
    partial = pdf_path.with_name(pdf_path.name + ".partial")
    partial.unlink(missing_ok=True)
    with tempfile.TemporaryDirectory(prefix="hilcal-pdf-") as profile:
        command = [browser, *FLAGS, f"--user-data-dir={profile}", f"--print-to-pdf={partial}",
                   Path(html_path).resolve().as_uri()]
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired:
            partial.unlink(missing_ok=True)
            raise PdfError(f"{browser} did not print {html_path} within {timeout_s:.0f} s") from None
        except OSError as e:
            raise PdfError(f"cannot start {browser}: {e}") from None
    if done.returncode != 0 or not partial.is_file() or partial.stat().st_size == 0:
        partial.unlink(missing_ok=True)
        tail = (done.stderr or "").strip().splitlines()[-3:]
        raise PdfError(f"{browser} exited with {done.returncode} and wrote no PDF: {' | '.join(tail)}")
    partial.replace(pdf_path)
    log.info("pdf_written", path=str(pdf_path), bytes=pdf_path.stat().st_size)
    return pdf_path
