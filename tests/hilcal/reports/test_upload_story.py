"""The upload's facts from a run's journal state: the commit's and the save's records read together, in words."""

from __future__ import annotations

from hilcal.reports.upload import upload_facts

COMMIT = {"operation": "upload", "endpoint": "tcp://127.0.0.1:1502", "outcome": "committed", "saved": False,
          "finished_at": "2026-11-27T10:00:01.5+00:00", "params_sha256": "ab" * 32, "live_readback_match": True,
          "staging_readback_match": True, "saved_readback_match": None}
SAVE = {"operation": "save", "endpoint": "tcp://127.0.0.1:1502", "outcome": "saved", "saved": True,
        "finished_at": "2026-11-27T10:00:03+00:00", "saved_readback_match": True}


def test_a_separate_save_is_read_from_its_own_record() -> None:
    facts = upload_facts({"outcome": "saved", "sha256": "ab" * 32, "record": COMMIT, "save_record": SAVE})
    assert facts is not None and facts.committed.done and facts.saved.done
    assert facts.saved.at == SAVE["finished_at"] and facts.committed.at == COMMIT["finished_at"]
    assert facts.summary() == "committed and saved to non-volatile memory; read back: matches"
    text = " ".join(facts.sentences())
    assert "Saved to non-volatile memory at 2026-11-27 10:00:03 UTC; the saved set read back matches." in text
    assert "Committed to the controller's live set on tcp://127.0.0.1:1502 at 2026-11-27 10:00:01 UTC" in text
    assert "Not saved" not in text


def test_a_commit_without_a_save_says_so() -> None:
    facts = upload_facts({"outcome": "committed", "record": COMMIT})
    assert facts is not None and facts.committed.done and not facts.saved.done
    assert facts.summary() == "committed (not saved); read back: matches"
    assert facts.sentences()[-1].startswith("Not saved to non-volatile memory")


def test_a_read_back_that_differs_is_said_everywhere() -> None:
    bad = {**COMMIT, "live_readback_match": False}
    facts = upload_facts({"outcome": "committed", "record": bad})
    assert facts is not None and facts.summary() == "committed (not saved); read back: DIFFERS"
    assert "the live set read back DIFFERS" in facts.sentences()[0]


def test_an_upload_that_failed_is_not_called_committed() -> None:
    failed = {**COMMIT, "outcome": "failed", "error": "ReadbackMismatch: staging differs at registers [3]",
              "live_readback_match": None}
    facts = upload_facts({"outcome": "started", "record": failed})
    assert facts is not None and not facts.committed.done and facts.summary() == "not committed"
    assert facts.sentences() == ["The new parameter set was not committed on tcp://127.0.0.1:1502: ReadbackMismatch: "
                                 "staging differs at registers [3]; the controller keeps the set it had."]


def test_nothing_uploaded() -> None:
    assert upload_facts(None) is None and upload_facts({}) is None
