"""Validators of I++ DME lines that check what NIST's response and command parsers check (test support code).

``check_response_line(line)`` and ``check_command_line(line)`` return the problems of one line (terminator removed;
empty = OK) in the words of NIST's parsers (``parserRes.cc``, ``parserCmd.cc`` of the 1.40-era suite): the tag, the
seventh and eighth characters, optional spaces (6.1.4.2), numbers (at most 16 digits, exponent of 1 to 3 digits),
strings, keywords, then each response's or command's own form (error texts and default severities of 8.2, the data
forms per method, items used twice, enumerations). ``command_problem(line)`` also gives the I++ error number NIST's
parser assigns. Written from NIST's documented rules, sharing no code or table with the driver or the simulator.

Four forms are newer in 1.4.3 than NIST's parsers; they are accepted and reported by ``version_notes(line)``:
``GetMachineClass(CartCMM)`` (6.3.2.8: an enumeration), error 0006's 1.4.3 text (8.2), ``Tool.AvrRadius()`` (6.3.13)
and ``Q()`` in OnPtMeasReport and its reports (6.3.2.6, 6.3.2.24). Errors 1011 and 1012 (8.2 of 1.4.3, unknown to
NIST's table) are accepted the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from tests.conformance import nist_commands, nist_responses
from tests.conformance.nist_tokens import Fail, Tokens, tokenize_command, tokenize_response, unspace


@dataclass(frozen=True)
class Problem:
    """What NIST's command parser would print, and the I++ error number it assigns."""

    message: str
    ipp_error: int


@dataclass
class _Result:
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    ipp_error: int | None = None


def _is_response(line: str) -> bool:
    return len(line) > 6 and line[6] in "&%#!"


def _response(line: str) -> _Result:
    out = _Result()
    try:
        tag = _response_tag(line)
        marker = line[6] if len(line) > 6 else ""
        if marker in "&%" and marker:
            if line[7:]:
                raise Fail("BAD CHARACTER AFTER RESPONSE END")
            if tag == "E0000":
                raise Fail("ZERO TAG MUST BE SERVER INITIATED RESPONSE")
            return out
        if marker not in ("!", "#"):
            raise Fail("BAD SEVENTH CHARACTER IN RESPONSE")
        if line[7:8] != " ":
            raise Fail("SPACE MISSING AT EIGHTH CHARACTER OF RESPONSE")
        text = unspace(line, 8)
        toks = tokenize_response(text)
        if marker == "!":
            nist_responses.error_response(toks, text, out.notes)
        elif tag == "E0000":
            nist_responses.server_initiated(toks, out.notes)
        else:
            nist_responses.data_response(toks, text, out.notes)
    except Fail as fail:
        out.problems.append(fail.message)
    return out


def _response_tag(line: str) -> str:
    if len(line) < 6 or not line[1:5].isdigit() or not line[1:5].isascii():
        raise Fail("BAD TAG CHARACTER")
    if line[5] != " ":
        raise Fail("SPACE MISSING AFTER TAG")
    if line[0] == "E":
        if line[1:5] == "0000" and line[6:7] not in ("!", "#"):
            raise Fail("ZERO TAG MUST BE SERVER INITIATED RESPONSE")
    elif line[0].isdigit() and line[0].isascii():
        if line[:5] == "00000":
            raise Fail("TAG NUMBER OUT OF RANGE FOR COMMAND TAG")
    else:
        raise Fail("BAD TAG CHARACTER")
    return line[:5]


def _command(line: str) -> _Result:
    out = _Result()
    name = ""
    try:
        is_event = _command_tag(line)
        text = unspace(line, 6)
        name, args_at = nist_commands.command_name(text)
        toks, end = tokenize_command(text, args_at)
        if text[end:]:
            raise Fail("BAD CHARACTER AFTER COMMAND END")
        if (name in nist_commands.EVENT_COMMANDS) != is_event:
            raise Fail("EVENT COMMAND MUST HAVE EVENT TAG" if not is_event
                       else "NON EVENT COMMAND MUST NOT HAVE EVENT TAG")
        nist_commands.check_arguments(name, Tokens(toks), out.notes)
    except Fail as fail:
        out.problems.append(f"{name}: {fail.message}" if name else fail.message)
        out.ipp_error = nist_commands.IPP_ERRORS[fail.message]
    return out


def _command_tag(line: str) -> bool:
    if len(line) < 6 or not line[1:5].isdigit() or not line[1:5].isascii():
        raise Fail("BAD TAG CHARACTER")
    if line[5] != " ":
        raise Fail("SPACE MISSING AFTER TAG")
    if line[0] == "E":
        if line[1:5] == "0000":
            raise Fail("TAG NUMBER OUT OF RANGE FOR EVENT TAG")
        return True
    if line[0].isdigit() and line[0].isascii():
        if line[:5] == "00000":
            raise Fail("TAG NUMBER OUT OF RANGE FOR COMMAND TAG")
        return False
    raise Fail("BAD TAG CHARACTER")


def check_response_line(line: str) -> list[str]:
    """The problems NIST's response parser finds in one response line (empty: a well-formed response)."""
    return _response(line).problems


def check_command_line(line: str) -> list[str]:
    """The problems NIST's command parser finds in one command line (empty: a well-formed command)."""
    return _command(line).problems


def command_problem(line: str) -> Problem | None:
    """NIST's command parser's message and I++ error number for a bad command line, None for a good one."""
    result = _command(line)
    if not result.problems:
        return None
    assert result.ipp_error is not None
    return Problem(result.problems[0], result.ipp_error)


def version_notes(line: str) -> list[str]:
    """The 1.4.3 forms a line uses that NIST's 1.40-era parsers do not know (accepted by the checks above)."""
    return (_response(line) if _is_response(line) else _command(line)).notes
