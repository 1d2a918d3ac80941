"""The upload's story, told once: what a run's upload did to the controller, as facts and in words.

A run's journal keeps the upload as ``{outcome, sha256, record, save_record, ...}``: ``record`` is the driver's record
of the commit (its ``saved`` is false when the save was a separate step) and ``save_record`` that of the save. Reading
one without the other is how a report said "saved" and "saved False" at once; every view (report.json's readers,
report.html, the certificate, the terminal, the panel) takes the facts from ``upload_facts`` instead.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Step:
    """One step of the upload with its own record: what happened, when, and whether the read-back matched."""

    done: bool
    at: str | None
    """The record's finish time (ISO 8601 UTC)."""
    readback_match: bool | None
    """True/False: read back and compared; None: not read back (or the step did not happen)."""
    error: str | None = None


@dataclass(frozen=True)
class UploadFacts:
    """What the controller holds after the run's upload, each fact from the record of the step that established it."""

    endpoint: str | None
    params_sha256: str | None
    committed: Step
    """The new set became the controller's live set, read back after the commit."""
    staging: Step
    """The staging area read back before the commit (devices without staging: not done)."""
    compensation: Step | None
    """The compensation block, in the same transaction as the geometry (None: no block uploaded)."""
    saved: Step
    """Copied to non-volatile memory and read back (the upload's own save, or the separate save's record)."""
    outcome: str | None

    def sentences(self) -> list[str]:
        """The facts in words, one sentence each (no keys, no codes)."""
        where = f" on {self.endpoint}" if self.endpoint else ""
        if not self.committed.done:
            why = f": {self.committed.error}" if self.committed.error else ""
            return [f"The new parameter set was not committed{where}{why}; the controller keeps the set it had."]
        out = [f"Committed to the controller's live set{where}{_at(self.committed.at)}; "
               f"{_readback(self.committed.readback_match, 'the live set')}."]
        if self.staging.readback_match is not None:
            out.append(f"Before the commit, {_readback(self.staging.readback_match, 'the staged set')}.")
        if self.compensation is not None:
            out.append(f"The compensation block went in the same transaction; "
                       f"{_readback(self.compensation.readback_match, 'the block')}.")
        if self.saved.done:
            out.append(f"Saved to non-volatile memory{_at(self.saved.at)}; "
                       f"{_readback(self.saved.readback_match, 'the saved set')}.")
        elif self.saved.error:
            out.append(f"Saving to non-volatile memory failed: {self.saved.error}.")
        else:
            out.append("Not saved to non-volatile memory: the controller holds the new set until it is switched off.")
        return out

    def summary(self) -> str:
        """One line for a terminal: committed/saved and whether everything read back matched."""
        if not self.committed.done:
            return "not committed"
        steps = [self.committed, self.staging, *([self.compensation] if self.compensation else []),
                 *([self.saved] if self.saved.done else [])]
        checks = [s.readback_match for s in steps if s.readback_match is not None]
        what = "committed and saved to non-volatile memory" if self.saved.done else "committed (not saved)"
        if not checks:
            return f"{what}; not read back"
        return f"{what}; read back: " + ("matches" if all(checks) else "DIFFERS")


def _at(iso_time: str | None) -> str:
    text = str(iso_time or "")
    return f" at {text[:19].replace('T', ' ')} UTC" if len(text) >= 19 else ""


def _readback(match: bool | None, what: str) -> str:
    return {True: f"{what} read back matches", False: f"{what} read back DIFFERS"}.get(match, f"{what} not read back")


def upload_facts(state: Mapping[str, Any] | None) -> UploadFacts | None:
    """The facts of a run's upload from its journal state (None: nothing was uploaded). A bare driver record (an
    upload whose state holds no ``record``) is read as its own commit record."""
    if not state:
        return None
    record: Mapping[str, Any] = state.get("record") or (state if "operation" in state else {})
    save: Mapping[str, Any] = state.get("save_record") or {}
    committed_outcomes = ("committed", "saved")
    committed = Step(done=record.get("outcome") in committed_outcomes or state.get("outcome") in committed_outcomes,
                     at=record.get("finished_at"), readback_match=record.get("live_readback_match"),
                     error=record.get("error"))
    staging = Step(done=record.get("staging_readback_match") is not None, at=None,
                   readback_match=record.get("staging_readback_match"))
    compensation = None if not record.get("compensation_sha256") else Step(
        done=committed.done, at=record.get("finished_at"), readback_match=record.get("compensation_readback_match"))
    if save:
        saved = Step(done=bool(save.get("saved")), at=save.get("finished_at"),
                     readback_match=save.get("saved_readback_match"), error=save.get("error"))
    else:
        saved = Step(done=bool(record.get("saved")), at=record.get("finished_at") if record.get("saved") else None,
                     readback_match=record.get("saved_readback_match"))
    return UploadFacts(endpoint=record.get("endpoint"),
                       params_sha256=record.get("params_sha256") or state.get("sha256"), committed=committed,
                       staging=staging, compensation=compensation, saved=saved,
                       outcome=state.get("outcome") or record.get("outcome"))
