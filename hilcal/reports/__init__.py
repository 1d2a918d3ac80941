"""Reports for people: the calibration run's report (JSON and a self-contained HTML page), its machine-time
section, its drift section (a machine's parameters across calibrations, with trend plots), the printable calibration
certificate, and the missing-physics diagnosis report with its plots.

May import everything else in ``hilcal`` (the calibration math, ``planning``, ``discovery``, ``acceptance``); nothing in
``hilcal`` imports the reports. A new report section is a function in the module of its report (``run``,
``timing`` or ``diagnosis``) that returns its JSON part and its HTML.

The names below load on first use (lazy_loader): a command that writes one report does not pay for the plotting
and statistics of the others at start-up.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "certificate": ["certificate_html"],
    "diagnosis": ["write_report"],
    "drift": ["drift_html", "trend_png"],
    "run": ["RunReport", "report_json", "write_run_report"],
    "timing": ["time_html", "time_section"],
})
