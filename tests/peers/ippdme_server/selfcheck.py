"""Self check of the I++ DME test peer (not a pytest file).

Run from anywhere::

    /work/main/.venv/bin/python tests/peers/ippdme_server/selfcheck.py

1. Runs a short session with a raw socket client against a server with two spheres
   (probing 5 points on a sphere, deliberate errors, error-state handling) and prints the
   transcript.
2. Replays the command lines of some NIST test programs (*.prg) and checks every response
   line with ``validate_response`` plus the per-transaction ``&`` ... ``%`` structure.
Exits with status 1 if a check fails.
"""

from __future__ import annotations

import re
import socket
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

if __package__:
    from .protocol import LineError, parse_tag, validate_response
    from .server import IppDmeServer
else:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from ippdme_server.protocol import LineError, parse_tag, validate_response
    from ippdme_server.server import IppDmeServer

NIST_DIR = Path("/work/shared/reference/ippdme/nist_test_files")
#: Errors that mean "the line was not understood" (tag, character and grammar errors).
SYNTAX_ERRORS = {1, 2, 7, 502, 507}
SPHERE_A = ((200.0, 100.0, -300.0), 12.5)
SPHERE_B = ((-250.0, 150.0, -320.0), 10.0)
_ERROR_RE = re.compile(r"! Error\((\d), (\d{4}),")


class RawClient:
    """Minimal line client that checks every response it receives."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.buffer = b""

    def close(self) -> None:
        self.sock.close()

    def _readline(self) -> str:
        while b"\r\n" not in self.buffer:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("server closed the connection")
            self.buffer += chunk
        line, self.buffer = self.buffer.split(b"\r\n", 1)
        return line.decode("ascii")

    def transact(self, line: str) -> list[str]:
        """Send one CommandLine; return all lines up to its ``%`` (or the E0000 error)."""
        self.sock.sendall(line.encode("latin-1") + b"\r\n")
        tag = line[:5]
        try:
            parse_tag(line)
            legal = True
        except LineError:
            legal = False
        lines: list[str] = []
        while True:
            response = self._readline()
            validate_response(response)
            lines.append(response)
            if legal and response == f"{tag} %":
                break
            if not legal and response.startswith("E0000 !"):
                break
        own = [resp for resp in lines if resp[:5] == tag]
        if legal:
            assert own[0] == f"{tag} &", f"{tag}: first response must be the Ack: {own}"
            assert [resp[6] for resp in own].count("%") == 1, f"{tag}: one % expected"
            assert [resp[6] for resp in own].count("&") == 1, f"{tag}: one & expected"
        return lines


def errors_of(lines: list[str]) -> list[int]:
    """Error numbers contained in response lines."""
    return [int(match.group(2)) for line in lines if (match := _ERROR_RE.search(line))]


def data_of(lines: list[str], tag: str) -> list[str]:
    return [line[8:] for line in lines if line.startswith(f"{tag} # ")]


def numbers_in(text: str) -> list[float]:
    return [float(v) for v in re.findall(r"[-+]?\d+\.\d+", text)]


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere through points: |p - c|^2 = r^2."""
    a = np.hstack([2.0 * points, np.ones((len(points), 1))])
    b = (points ** 2).sum(axis=1)
    solution, *_ = np.linalg.lstsq(a, b, rcond=None)
    centre = solution[:3]
    return centre, float(np.sqrt(solution[3] + centre @ centre))


class Check:
    """Collects pass/fail results."""

    def __init__(self) -> None:
        self.failures: list[str] = []

    def __call__(self, ok: bool, what: str) -> None:
        print(f"  [{'ok' if ok else 'FAIL'}] {what}")
        if not ok:
            self.failures.append(what)


def session_demo(check: Check) -> None:
    """Short session: home, tool, probing parameters, 5 points on sphere A, errors."""
    print("=== session demo")
    server = IppDmeServer(lambda: [SPHERE_A, SPHERE_B], stylus_radius_mm=1.5, seed=1)
    client = RawClient(server.port)
    second = RawClient(server.port)
    try:
        t = client.transact
        t("00001 StartSession()")
        check(errors_of(second.transact("00001 StartSession()")) == [8],
              "second client's StartSession gets 0008 Protocol error")
        check(errors_of(t("00002 StartSession()")) == [8], "second StartSession gets 0008")
        t("00003 ClearAllErrors()")
        homed = data_of(t("00004 IsHomed()"), "00004")
        if homed == ["IsHomed(0)"]:
            t("00005 Home()")
        check(data_of(t("00006 IsHomed()"), "00006") == ["IsHomed(1)"], "machine is homed")
        check(data_of(t("00007 GetDMEVersion()"), "00007") == ['DMEVersion("1.4.3")'],
              "GetDMEVersion")
        t("00008 EnumTools()")
        t('00009 ChangeTool("Probe1")')
        radius = data_of(t("00010 GetProp(Tool.AvrRadius())"), "00010")
        check(radius == ["Tool.AvrRadius(1.500000)"], "AvrRadius equals the stylus radius")
        t("00011 SetProp(Tool.PtMeasPar.Approach(3), Tool.PtMeasPar.Search(5), "
          "Tool.PtMeasPar.Retract(2))")
        t("00012 GetProp(Tool.PtMeasPar.Approach(), Tool.PtMeasPar.Search(), "
          "Tool.PtMeasPar.Retract())")
        t("00013 OnPtMeasReport(X(), Y(), Z(), IJK(), ER())")

        centre, big_r = np.array(SPHERE_A[0]), SPHERE_A[1]
        directions = [np.array([0.0, 0.0, 1.0])]
        for azimuth in (0.0, 90.0, 180.0, 270.0):
            a, e = np.radians(azimuth), np.radians(30.0)
            directions.append(np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a),
                                        np.sin(e)]))
        points = []
        tag = 20
        for n in directions:
            nominal = centre + big_r * n
            above = centre + (big_r + 1.5 + 3.0) * n
            t(f"{tag:05d} GoTo(X({above[0]:.4f}), Y({above[1]:.4f}), Z({centre[2] + 40:.4f}))")
            tag += 1
            lines = t(f"{tag:05d} PtMeas(X({nominal[0]:.4f}), Y({nominal[1]:.4f}), "
                      f"Z({nominal[2]:.4f}), IJK({n[0]:.6f}, {n[1]:.6f}, {n[2]:.6f}))")
            values = numbers_in(data_of(lines, f"{tag:05d}")[0])
            points.append(values[:3])
            tag += 1
            t(f"{tag:05d} GoTo(Z({centre[2] + 40:.4f}))")
            tag += 1
        fitted_centre, fitted_radius = fit_sphere(np.array(points))
        check(bool(np.linalg.norm(fitted_centre - centre) < 0.01),
              f"ball centres fit sphere A centre (off by "
              f"{np.linalg.norm(fitted_centre - centre) * 1000:.2f} um)")
        check(abs(fitted_radius - (big_r + 1.5)) < 0.01,
              f"fitted radius {fitted_radius:.4f} = sphere + stylus radius {big_r + 1.5}")

        lines = t("00100 PtMeas(X(0), Y(0), Z(-100), IJK(0, 0, 1))")
        check(errors_of(lines) == [1006], "PtMeas in free space: 1006 Surface not found")
        check(data_of(t("E0101 GetErrStatusE()"), "E0101") == ["ErrStatus(1)"],
              "GetErrStatusE reports the error state")
        check(errors_of(t("00102 GetErrorInfo(1006)")) == [511, 514],
              "GetErrorInfo in error state: 0511 + 0514")
        t("00103 ClearAllErrors()")
        check(data_of(t("00104 GetErrorInfo(1006)"), "00104") == ['"Surface not found"'],
              "GetErrorInfo after ClearAllErrors")
        t(f"00105 GoTo(X({centre[0]}), Y({centre[1]}), Z({centre[2] + 60}))")
        lines = t(f"00106 GoTo(Z({centre[2] - 60}))")
        check(errors_of(lines) == [2504], "GoTo through sphere A: 2504 Collision")
        t("00107 ClearAllErrors()")
        check(errors_of(t("00108 Frobnicate()")) == [501], "unknown command: 0501")
        t("00111 ClearAllErrors()")
        check(errors_of(t("00109 GoTo(X(1.2 E2))")) == [502], "illegal space: 0502")
        t("00118 ClearAllErrors()")
        check(errors_of(t("A0110 Get(X())")) == [1], "illegal tag: E0000 0001")
        t("00119 ClearAllErrors()")
        t("E0113 OnMoveReportE(Dis(1), X(), Y(), Z())")
        lines = t("00114 GoTo(Z(-200))")
        check(any(line.startswith("E0113 # X(") for line in lines), "OnMoveReportE reports")
        t("00115 StopDaemon(E0113)")
        t("00116 SetProp(Tool.PtMeasPar.Speed(1000))")
        check(data_of(t("00117 GetProp(Tool.PtMeasPar.Speed())"), "00117")
              == ["Tool.PtMeasPar.Speed(50.000000)"], "out of range SetProp clamped to Max")
        t("09999 EndSession()")
        second.transact("00001 StartSession()")
        second.transact("00002 EndSession()")
    finally:
        client.close()
        second.close()
        server.close()
    print(f"--- transcript ({server.commands} commands)")
    for direction, line in server.transcript:
        arrow = {"client": "C>", "server": " <S", "note": "  ~"}[direction]
        print(f"{arrow} {line}")


def program_lines(name: str) -> list[str]:
    text = (NIST_DIR / f"{name}.prg").read_text(encoding="latin-1")
    return [line.rstrip("\r\n") for line in text.splitlines()
            if line and not line.startswith(("\\", ":"))]


def replay(name: str, auto_clear: bool = False) -> list[tuple[str, list[str]]]:
    """Replay a NIST program; return (command line, response lines) pairs.

    With ``auto_clear`` a ClearAllErrors follows every error of severity >= 2 so that each
    line of the program is judged on its own.
    """
    server = IppDmeServer(lambda: [SPHERE_A, SPHERE_B], seed=2)
    client = RawClient(server.port)
    results: list[tuple[str, list[str]]] = []
    try:
        for line in program_lines(name):
            responses = client.transact(line)
            results.append((line, responses))
            if auto_clear and any(code not in (504, 512) for code in errors_of(responses)):
                client.transact("09990 ClearAllErrors()")
    finally:
        client.close()
        server.close()
    return results


def nist_replays(check: Check) -> None:
    print("=== NIST program replays")
    for name in ("GetProp", "SetProp", "Home_Test", "StopDaemon", "GetErrorInfo",
                 "SetCsyTransformation"):
        results = replay(name)
        kinds = Counter(resp[6] for _, responses in results for resp in responses)
        codes = [code for _, responses in results for code in errors_of(responses)]
        print(f"  {name}: {len(results)} commands, responses {dict(kinds)}, errors {codes}")
        expected = [513] if name == "StopDaemon" else []
        check(codes == expected, f"{name}: all responses well formed, errors {expected}")
        if name in ("Home_Test", "SetCsyTransformation"):
            for line, responses in results:
                if " Get(" in line:
                    print(f"      {line[6:]:<22} -> {data_of(responses, line[:5])[0]}")
    for name in ("numbersCmdOK", "allCmdOK"):
        results = replay(name, auto_clear=True)
        syntax = [(line, errors_of(responses)) for line, responses in results
                  if SYNTAX_ERRORS & set(errors_of(responses))]
        found = Counter(code for _, responses in results for code in errors_of(responses))
        print(f"  {name}: {len(results)} commands, error numbers {dict(found)}")
        check(not syntax, f"{name}: every line is accepted by the parser {syntax[:3]}")
    results = replay("numbersErrorCmd", auto_clear=True)
    bad = [line for line, responses in results
           if "GoTo" in line and not SYNTAX_ERRORS & set(errors_of(responses))]
    check(not bad, f"numbersErrorCmd: every malformed number rejected {bad}")


def main() -> int:
    began = time.monotonic()
    check = Check()
    session_demo(check)
    nist_replays(check)
    print(f"=== {len(check.failures)} failure(s), {time.monotonic() - began:.2f} s")
    return 1 if check.failures else 0


if __name__ == "__main__":
    sys.exit(main())
