"""Declarative protocol definitions shared by ``drivers`` and ``sim_devices``; data and tiny pure helpers only.

Controller: ``controller.dbc`` (hilcal's own CAN frames), ``controller_states`` (state, command, reason and fault
codes), ``modbus_maps/`` with ``modbus_map`` (Modbus register map files and their schema) and ``registers`` (their
enums and word helpers), ``canopen/`` (EDS files), ``checksums`` (CRC-8/-16/-32); see docs/protocols.md and
docs/controllers.md. CMM: ``ippdme`` (I++ DME 1.4.3). Laser tracker: ``emscon``.
Configuration files the tools exchange (station, simulator): ``toml_text`` writes their TOML.
"""

from __future__ import annotations

from importlib import resources

CONTROLLER_DBC = "controller.dbc"


def controller_dbc_text() -> str:
    """Text of the controller CAN database (package data ``hilcal/protocols/controller.dbc``)."""
    return resources.files(__name__).joinpath(CONTROLLER_DBC).read_text()
