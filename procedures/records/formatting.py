"""``hilcal history`` as plain text: one line per run (its uploads indented beneath) or stand-alone upload."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def _brief(verify: Mapping[str, Any] | None) -> str:
    if not verify or verify.get("max_position_mm") is None:
        return "-"
    return f"{verify['max_position_mm']:.4f}"


def format_history(rows: list[dict[str, Any]]) -> str:
    """history() as a plain-text table: one line per run (uploads indented beneath) or standalone upload."""
    if not rows:
        return "no runs or uploads recorded"
    header = (f"{'time (UTC)':<26} {'run / operation':<24} {'status':<11} {'machine':<22} {'est':<5} "
              f"{'operator':<10} {'max pos before mm':>17} {'max pos after mm':>16}")
    lines = [header, "-" * len(header)]

    def upload_line(u: Mapping[str, Any], indent: str) -> str:
        rec = u.get("record") or {}
        sha = (u.get("params_sha256") or "")[:12]
        what = f"{indent}{rec.get('operation', 'upload')}"
        error = f"  {rec['error']}" if rec.get("error") else ""
        return (f"{(u.get('time') or '')[:26]:<26} {what:<24} {u.get('outcome') or '':<11} "
                f"{u.get('endpoint') or '':<30} {u.get('operator') or '':<10} sha256 {sha}{error}")

    for row in rows:
        if row.get("kind") == "upload":
            lines.append(upload_line(row, ""))
            continue
        lines.append(
            f"{(row.get('started_at') or '')[:26]:<26} {row['run_id'][:24]:<24} {row.get('status') or '':<11} "
            f"{(row.get('machine') or row.get('robot_name') or '')[:22]:<22} {row.get('estimator') or '':<5} "
            f"{(row.get('operator') or '')[:10]:<10} {_brief(row.get('verify_before')):>17} "
            f"{_brief(row.get('verify_after')):>16}"
        )
        if row.get("verdict"):
            lines.append(f"{'':<26}   sign-off: {row['verdict']}, certificate {row.get('certificate_number') or '-'} "
                         f"{row.get('certificate_path') or ''}".rstrip())
        lines += [upload_line(u, "  ") for u in row.get("uploads", [])]
    return "\n".join(lines)
