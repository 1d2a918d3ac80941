"""Calibration records: every run, parameter set and controller upload of every machine, in SQLite (one file per
station, the default) or PostgreSQL (one database for a plant), with Alembic migrations.

``Records`` is the database (``store.py``); ``database.py`` turns a path or URL into an engine; ``migrate.py``
upgrades a database in place; ``sync.py`` stages a run's records in its journal so a lost database delays them
but never loses them; ``uploads.py`` holds the operator's upload and rollback; ``formatting.py`` the text history.
"""

from procedures.records.database import RecordsError, RecordsUnavailable, default_target, records_url, redact
from procedures.records.formatting import format_history
from procedures.records.store import (
    PARAMETER_KEYS,
    RUN_FIELDS,
    Records,
    Source,
    machine_identity,
    now_iso,
    parameter_set_sha256,
)
from procedures.records.uploads import (
    PARAMETER_NAMES,
    ParameterFileError,
    UploadDeclined,
    format_diff,
    parameter_diff,
    read_parameter_file,
    rollback_controller,
    upload_parameter_file,
)

__all__ = [
    "PARAMETER_KEYS",
    "PARAMETER_NAMES",
    "RUN_FIELDS",
    "ParameterFileError",
    "Records",
    "RecordsError",
    "RecordsUnavailable",
    "Source",
    "UploadDeclined",
    "default_target",
    "format_diff",
    "format_history",
    "machine_identity",
    "now_iso",
    "parameter_diff",
    "parameter_set_sha256",
    "read_parameter_file",
    "records_url",
    "redact",
    "rollback_controller",
    "upload_parameter_file",
]
