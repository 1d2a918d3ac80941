"""The NIST-mirroring validators against NIST's own good and bad examples (and NIST's words for the bad ones).

Every entry of NIST's good files passes; every entry of its bad files fails with the message NIST's parser printed
(``.txt``) and, for commands, the I++ error number it assigned; the only exceptions are the 1.4.3 forms NIST's
1.40-era parsers do not know, which must pass and be named by ``version_notes``.
"""

from __future__ import annotations

import pytest

from tests.conformance.nist_files import Outcome, nist_dir, programs, read_entries, read_log, read_outcomes
from tests.conformance.nist_grammar import check_command_line, check_response_line, command_problem, version_notes

NIST = nist_dir()
pytestmark = pytest.mark.skipif(NIST is None, reason="NIST's I++ DME test files are not available here")

BAD_RESPONSE_FILES = {"parserResErrors.res": "parserResErrors.txt", "numbersErrorRes.res": "numbersErrorRes.txt"}
BAD_COMMAND_FILES = {"parserCmdErrors.prg": "parserCmdErrors.txt", "numbersErrorCmd.prg": "numbersErrorCmd.txt"}
NEWER_IN_1_4_3 = {
    "E0000 # GoTo(Q(1))": "Q",
    "02314 # X(3), Q(4)": "Q",
    "03114 OnPtMeasReport(Q())": "Q",
}
"""Bad examples of NIST's that are good 1.4.3 (Q() may be reported, 6.3.2.6 and 6.3.2.24)."""


def _same_message(found: str, nist: str) -> bool:
    """NIST's .txt files print the method's name before the message, except numbersError*.txt."""
    return found == nist or (": " not in nist and found.split(": ", 1)[-1] == nist)


@pytest.mark.parametrize("name", ["allResOK.res", "numbersResOK.res", "errorResponses.res"])
def test_every_good_response_passes(name: str) -> None:
    assert NIST is not None
    entries = read_entries(NIST / name)
    assert len(entries) > 20
    bad = {e.text: check_response_line(e.text) for e in entries if check_response_line(e.text)}
    assert not bad
    assert not [e.text for e in entries if version_notes(e.text)]  # NIST's forms are no version difference


def test_error_responses_cover_the_whole_table_with_its_texts() -> None:
    """errorResponses.txt: one correct response for each of the 50 errors; changing a text or a severity fails."""
    assert NIST is not None
    entries = read_entries(NIST / "errorResponses.res")
    assert len(entries) == 50
    for entry in entries:
        text = entry.text
        assert check_response_line(text.replace('")', 'x")')) == ["ErrorResponse: BAD TEXT"]
        severity = text[14]
        wrong = "3" if severity != "3" else "2"
        assert check_response_line(text[:14] + wrong + text[15:]) == ["ErrorResponse: BAD SEVERITY"]


@pytest.mark.parametrize("res", sorted(BAD_RESPONSE_FILES))
def test_every_bad_response_fails_with_nists_message(res: str) -> None:
    assert NIST is not None
    entries = read_entries(NIST / res)
    outcomes = read_outcomes(NIST / BAD_RESPONSE_FILES[res], entries)
    assert len(outcomes) == len(entries)
    wrong: list[tuple[str, list[str], str]] = []
    for outcome in outcomes:
        text = outcome.entry.text
        problems = check_response_line(text)
        if text in NEWER_IN_1_4_3:
            assert not problems and version_notes(text), text
            continue
        if not problems or not _same_message(problems[0], outcome.message):
            wrong.append((text, problems, outcome.message))
    assert not wrong


def _command_outcomes(prg: str) -> list[Outcome]:
    assert NIST is not None
    return read_outcomes(NIST / BAD_COMMAND_FILES[prg], read_entries(NIST / prg))


@pytest.mark.parametrize("prg", sorted(BAD_COMMAND_FILES))
def test_every_bad_command_fails_with_nists_message_and_error_number(prg: str) -> None:
    outcomes = _command_outcomes(prg)
    rejected = [o for o in outcomes if not o.accepted]
    assert len(rejected) >= 7
    wrong = []
    for outcome in outcomes:
        text = outcome.entry.text
        problem = command_problem(text)
        if outcome.accepted:
            assert problem is None, text
        elif text in NEWER_IN_1_4_3:
            assert problem is None and version_notes(text), text
        elif (problem is None or not _same_message(problem.message, outcome.message)
              or problem.ipp_error != outcome.ipp_error):
            wrong.append((text, problem, outcome.message, outcome.ipp_error))
    assert not wrong


def test_parser_cmd_errors_reach_every_kind_of_error() -> None:
    """The bad commands cover all the error numbers NIST's parser gives: 0001, 0002, 0502, 0507, 0509 and 1007."""
    numbers = {o.ipp_error for o in _command_outcomes("parserCmdErrors.prg") if not o.accepted}
    assert numbers == {1, 2, 502, 507, 509, 1007}


def test_every_other_program_passes_the_command_checks() -> None:
    """NIST's programs hold good commands only (checkerCmdErrors.prg: all but one theta out of range, per its .txt)."""
    failing: dict[str, list[str]] = {}
    for path in programs():
        if path.name in BAD_COMMAND_FILES:
            continue
        bad = [e.text for e in read_entries(path) if check_command_line(e.text)]
        if bad:
            failing[path.name] = bad
    assert failing == {"checkerCmdErrors.prg": ["04601 SetCsyTransformation(PartCsy, 0, 0, 0, 180.1, 0, 0)"]}
    assert len(programs()) >= 60


@pytest.mark.parametrize(("line", "note"), [
    ("00010 # GetMachineClass(CartCMM)", "GetMachineClass"),
    ("00010 # GetMachineClass(CartCMMWithRotaryTable)", "GetMachineClass"),
    ('00011 ! Error(2, 0006, "GoTo", "Transaction aborted (Use ClearAllErrors To Continue)")', "0006"),
    ("00012 GetProp(Tool.AvrRadius())", "AvrRadius"),
    ("00012 # Tool.AvrRadius(1.5)", "AvrRadius"),
    ("00012 # Tool.Name(\"Probe1\"), Tool.AvrRadius(1.5)", "AvrRadius"),
    ("E0012 GetPropE(Tool.AvrRadius())", "AvrRadius"),
    ("00013 OnPtMeasReport(X(), Y(), Z(), Q())", "Q"),
    ("00014 # X(1), Y(2), Z(3), Q(0)", "Q"),
])
def test_the_four_version_differences_pass_and_are_named(line: str, note: str) -> None:
    checked = check_response_line(line) if line[6] in "#!" else check_command_line(line)
    assert checked == []
    [found] = version_notes(line)
    assert note in found and found.startswith("1.4.3")


@pytest.mark.parametrize(("line", "problem"), [
    ("00010 # GetMachineClass(HorseCMM)", "BAD KEYWORD"),
    ("00010 # GetMachineClass(PartCsy)", "GetMachineClassResponse: BAD RESPONSE ITEMS"),
    ('00011 ! Error(2, 0006, "GoTo", "Transaction aborted ...: after error 1006")', "ErrorResponse: BAD TEXT"),
    ("00012 GetProp(FoundTool.AvrRadius())", "GetProp: ARGUMENT SECOND PART BAD"),
    ("00012 # FoundTool.AvrRadius(1.5)", "GetPropResponse: BAD SECOND KEYWORD"),
    ("00013 OnPtMeasReport(Q(), Q())", "OnPtMeasReport: Q ARGUMENT USED TWICE"),
    ('00000 ! Error(2, 0001, "", "Illegal tag")', "TAG NUMBER OUT OF RANGE FOR COMMAND TAG"),
    ('E0000 ! Error(2, 0001, "", "Illegal tag")', "BAD STRING"),
    ('00020 # ErrorInfo(1006, "Surface not found")', "BAD CHARACTER AFTER KEYWORD"),
    ('00021 ! Error(2, 2504, "GoTo", "Collision")', "ErrorResponse: BAD SEVERITY"),
    ('00022 ! Error(3, 2504, GoTo, "Collision")', "ErrorResponse: BAD RESPONSE ITEMS"),
    ("00023 # X(1), Y(2), X(3)", "PtMeasOrGetResponse: X USED TWICE"),
    ("00024 GoTo(X(1)) ", None),
    ("00024 GoTo (X(1))", None),
    ("00025  GoTo(X(1))", "ILLEGAL SPACE"),
])
def test_hand_made_lines(line: str, problem: str | None) -> None:
    checked = check_response_line(line) if line[6] in "#!&%" else check_command_line(line)
    assert checked == ([problem] if problem else [])


def test_the_reference_servers_transcripts_pass_but_for_its_miswritten_texts() -> None:
    """A peer we did not write: every line NIST's reference server sent (ClientServerLogs) passes, except the errors
    whose text it capitalised unlike 8.2 ("Incorrect Arguments", "Bad Argument"), which the validator must catch."""
    assert NIST is not None
    sent = [record.text for path in sorted((NIST / "ClientServerLogs").glob("*Server.log"))
            for record in read_log(path) if record.direction == "sent"]
    assert len(sent) > 4000
    failing = [line for line in sent if check_response_line(line)]
    assert {check_response_line(line)[0] for line in failing} == {"ErrorResponse: BAD TEXT"}
    assert {line.rsplit(", ", 1)[1] for line in failing} == {'"Incorrect Arguments")', '"Bad Argument")'}
    client = read_log(NIST / "ClientServerLogs" / "PtMeas_Client.log")
    assert (client[0].direction, client[0].text) == ("sent", "00001 StartSession()")
    assert (client[1].direction, client[1].text) == ("received", "00001 &")
