"""Modbus fault injection for the simulated controller: exception responses, corrupted writes, dropped connections.

Switchable at start (``ModbusFaultConfig``) and at run time, e.g. to drop the link in the middle of an upload.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from hilcal.protocols.registers import ModbusExceptionCode
from sim_devices.controller.modbus_frames import WRITE_MULTIPLE, ModbusRequest
from sim_devices.controller.state_machine import ModbusFaultConfig


@dataclass
class _ExceptionRule:
    code: ModbusExceptionCode
    remaining: int
    function: int | None
    address: int | None
    skip: int = 0


@dataclass(frozen=True)
class FaultAction:
    """What the fault injector decided for one request."""

    kind: str = "pass"
    code: ModbusExceptionCode | None = None
    execute: bool = False


class ModbusFaultInjector:
    """Exception responses and dropped connections, switchable at start (ModbusFaultConfig) and at run time."""

    def __init__(self, config: ModbusFaultConfig | None = None) -> None:
        cfg = config or ModbusFaultConfig()
        self._lock = threading.Lock()
        self._rules: list[_ExceptionRule] = []
        self._corrupt_writes = 0
        self._corrupt_skip = 0
        self._drop_in: int | None = cfg.drop_after_writes
        self._drop_execute = cfg.execute_dropped_write
        self._always: ModbusExceptionCode | None = (
            ModbusExceptionCode(cfg.exception_code) if cfg.exception_code is not None else None
        )
        self.response_delay_s = cfg.response_delay_s

    def drop_connection_at_write(self, n: int, *, execute: bool = False) -> None:
        """Close the connection when the n-th write request from now arrives (1 = the next one), once.

        execute=True: that write is carried out before the connection closes (its response is lost).
        """
        if n < 1:
            raise ValueError("n counts from 1")
        with self._lock:
            self._drop_in = n
            self._drop_execute = execute

    def exception_next(
        self,
        code: ModbusExceptionCode,
        count: int = 1,
        *,
        function: int | None = None,
        address: int | None = None,
        skip: int = 0,
    ) -> None:
        """Answer ``count`` matching requests, after letting ``skip`` through, with an exception (not executed)."""
        with self._lock:
            self._rules.append(_ExceptionRule(code, count, function, address, skip))

    def corrupt_next_write(self, count: int = 1, *, skip: int = 0) -> None:
        """Flip the lowest bit of the first value of ``count`` FC16 requests, after letting ``skip`` through (a flaky
        link or firmware)."""
        with self._lock:
            self._corrupt_writes += count
            self._corrupt_skip = skip

    def exception_always(self, code: ModbusExceptionCode | None) -> None:
        """Answer every request with this exception (None: back to normal)."""
        with self._lock:
            self._always = code

    def clear(self) -> None:
        with self._lock:
            self._rules.clear()
            self._corrupt_writes = 0
            self._drop_in = None
            self._always = None

    def decide(self, request: ModbusRequest) -> FaultAction:
        with self._lock:
            if self._always is not None:
                return FaultAction("exception", self._always)
            if request.is_write and self._drop_in is not None:
                self._drop_in -= 1
                if self._drop_in == 0:
                    self._drop_in = None
                    return FaultAction("drop", execute=self._drop_execute)
            for rule in self._rules:
                if rule.function in (None, request.function) and rule.address in (None, request.address):
                    if rule.skip > 0:
                        rule.skip -= 1
                        continue
                    rule.remaining -= 1
                    if rule.remaining <= 0:
                        self._rules.remove(rule)
                    return FaultAction("exception", rule.code)
            if request.function == WRITE_MULTIPLE and self._corrupt_writes > 0:
                if self._corrupt_skip > 0:
                    self._corrupt_skip -= 1
                    return FaultAction()
                self._corrupt_writes -= 1
                return FaultAction("corrupt")
            return FaultAction()
