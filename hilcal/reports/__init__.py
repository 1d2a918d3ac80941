"""Reports for people: the calibration run's report (JSON and a self-contained HTML page), its machine-time
section, its drift section (a machine's parameters across calibrations, with trend plots), the printable calibration
certificate, and the missing-physics diagnosis report with its plots.

May import everything else in ``hilcal`` (the calibration math, ``planning``, ``discovery``, ``acceptance``); nothing in
``hilcal`` imports the reports. A new report section is a function in the module of its report (``run``,
``timing`` or ``diagnosis``) that returns its JSON part and its HTML.
"""

from hilcal.reports.certificate import certificate_html
from hilcal.reports.diagnosis import write_report
from hilcal.reports.drift import drift_html, trend_png
from hilcal.reports.run import RunReport, report_json, write_run_report
from hilcal.reports.timing import time_html, time_section

__all__ = ["RunReport", "certificate_html", "drift_html", "report_json", "time_html", "time_section", "trend_png",
           "write_report", "write_run_report"]
