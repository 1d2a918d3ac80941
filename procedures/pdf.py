"""Print an HTML page to PDF with WeasyPrint: the page's own print CSS (``@page`` size and margins) sets the paper.

WeasyPrint (BSD, from PyPI) lays the page out with Pango, a system library every station already has, so no browser
is needed for a PDF. It runs in a child Python process with a bounded time, so that a slow layout or a crash in its
native libraries cannot take the run down with it; the child fetches local files only (no network), writes to a
temporary name and the parent renames it, so a failed print leaves no PDF. Run as ``python -m procedures.pdf HTML PDF``.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import structlog

log = structlog.get_logger(__name__)

TIMEOUT_S = 60.0
ALLOWED_PROTOCOLS = ("file", "data")
"""What the page may load: files beside it and data: URLs; never the network."""
INSTALL = ("pip install 'weasyprint>=68,<71' (hilcal's dependency) and Debian's libpango-1.0-0 libpangoft2-1.0-0 "
           "fonts-dejavu-core")


class PdfError(RuntimeError):
    """No PDF was written (WeasyPrint missing or failed); the message says why and how to fix it."""


def print_to_pdf(html_path: Path, pdf_path: Path, *, timeout_s: float = TIMEOUT_S) -> Path:
    """Write pdf_path from the HTML file (written to a temporary name first, so a failed print leaves no PDF)."""
    html_path = Path(html_path).resolve()
    if not html_path.is_file():
        raise PdfError(f"{html_path} does not exist")
    partial = pdf_path.with_name(pdf_path.name + ".partial")
    partial.unlink(missing_ok=True)
    root = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)}
    command = [sys.executable, "-m", "procedures.pdf", str(html_path), str(partial.resolve())]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, check=False, env=env)
    except subprocess.TimeoutExpired:
        partial.unlink(missing_ok=True)
        raise PdfError(f"WeasyPrint did not print {html_path} within {timeout_s:g} s") from None
    except OSError as e:
        raise PdfError(f"cannot start {sys.executable}: {e}") from None
    if done.returncode != 0 or not partial.is_file() or partial.stat().st_size == 0:
        partial.unlink(missing_ok=True)
        tail = " | ".join((done.stderr or "").strip().splitlines()[-3:])
        raise PdfError(f"WeasyPrint exited with {done.returncode} and wrote no PDF: {tail}")
    for note in (done.stdout or "").splitlines():
        log.info("pdf_layout_note", note=note)
    partial.replace(pdf_path)
    log.info("pdf_written", path=str(pdf_path), bytes=pdf_path.stat().st_size)
    return pdf_path


class _Notes(logging.Handler):
    """WeasyPrint's warnings (CSS it ignores, files it cannot load), one a line on stdout for the parent's log."""

    def emit(self, record: logging.LogRecord) -> None:
        print(record.getMessage().replace("\n", " "), flush=True)


def _render(html_path: str, pdf_path: str) -> int:
    """The child: lay the page out and write the PDF; exit 2 (with the reason on stderr) if WeasyPrint cannot."""
    try:
        from weasyprint import HTML, URLFetcher
    except (ImportError, OSError) as e:  # OSError: WeasyPrint found no Pango to load
        print(f"WeasyPrint cannot be loaded ({e}); install {INSTALL}", file=sys.stderr)
        return 2
    logging.getLogger("weasyprint").addHandler(_Notes(logging.WARNING))
    fetcher = URLFetcher(allowed_protocols=ALLOWED_PROTOCOLS, timeout=5)
    HTML(filename=html_path, url_fetcher=fetcher, media_type="print").write_pdf(pdf_path)
    return 0


if __name__ == "__main__":
    if len(sys.argv) != 3:
        print("usage: python -m procedures.pdf HTML PDF", file=sys.stderr)
        sys.exit(2)
    sys.exit(_render(sys.argv[1], sys.argv[2]))
