"""What a station file says for the sign-off: acceptance limits, the CMM's identity and calibration, the station's
name, the machine's serial and the operator; read in full from a real station, or alone for a ``--sim`` run.

The ``[acceptance]`` section holds upper limits (all optional) and the decision rule::

    [acceptance]
    max_position_mm = 0.05         # verification poses after calibration: largest position error
    rms_position_mm = 0.02
    max_orientation_deg = 0.005
    rms_orientation_deg = 0.002
    ap_position_mm = 0.05          # ISO 9283 pose accuracy AP_P at every test pose (needs --acceptance iso9283)
    rp_position_mm = 0.02          # ISO 9283 pose repeatability RP_l
    ap_orientation_deg = 0.005     # |AP_a|, |AP_b|, |AP_c|
    rp_orientation_deg = 0.005     # RP_a, RP_b, RP_c
    decision_rule = "iso14253-1"   # or "simple"

    [cmm]                          # besides url, alignment, ...: the instrument on the certificate
    identity = "Leitz PMM-C 12.10.7, serial 4711"
    stated_uncertainty_mm = 0.004  # expanded U (k = 2) of one measured sphere-centre coordinate
    calibration_due = 2027-03-31   # the CMM's own calibration
"""

from __future__ import annotations

import datetime as dt
import tomllib
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hilcal.acceptance.verdict import LIMITS


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SignoffFileError(ValueError):
    """A station file whose sign-off settings cannot be read."""


def _limit(key: str) -> Any:
    label, unit = LIMITS[key]
    return Field(default=None, gt=0, description=f"{label}, {unit}")


class AcceptanceSection(_Strict):
    """Upper limits that sign off the calibrated machine (unset ones are not checked) and the decision rule."""

    max_position_mm: float | None = _limit("max_position_mm")
    rms_position_mm: float | None = _limit("rms_position_mm")
    max_orientation_deg: float | None = _limit("max_orientation_deg")
    rms_orientation_deg: float | None = _limit("rms_orientation_deg")
    ap_position_mm: float | None = _limit("ap_position_mm")
    rp_position_mm: float | None = _limit("rp_position_mm")
    ap_orientation_deg: float | None = _limit("ap_orientation_deg")
    rp_orientation_deg: float | None = _limit("rp_orientation_deg")
    decision_rule: Literal["iso14253-1", "simple"] = Field(
        default="iso14253-1", description="iso14253-1: a figure passes only with its uncertainty inside the limit; "
        "simple: its value decides")

    def limits(self) -> dict[str, float]:
        """The limits that are set, by key of ``hilcal.acceptance.verdict.LIMITS``."""
        return {k: v for k in LIMITS if (v := getattr(self, k)) is not None}

    def needs_iso9283(self) -> bool:
        return any(k.startswith(("ap_", "rp_")) for k in self.limits())


class CmmIdentity(_Strict):
    """The CMM as the certificate names it: identity, stated uncertainty and its own calibration's due date."""

    identity: str | None = Field(default=None, min_length=1, max_length=200, description="make, model and serial")
    stated_uncertainty_mm: float | None = Field(
        default=None, gt=0, le=1.0, description="expanded uncertainty U (k = 2) of one measured sphere-centre "
        "coordinate, from the CMM's calibration certificate")
    calibration_due: dt.date | None = Field(default=None, description="the CMM's own calibration is due then")


class SignoffSettings(_Strict):
    """The sign-off part of a station file (every part optional)."""

    name: str | None = Field(default=None, min_length=1, max_length=100)
    operator: str | None = None
    machine_serial: str | None = Field(default=None, min_length=1, max_length=100)
    acceptance: AcceptanceSection = Field(default_factory=AcceptanceSection)
    cmm: CmmIdentity = Field(default_factory=CmmIdentity)
    station_file: str | None = None
    cmm_uncertainty_source: str | None = None
    """Where ``cmm.stated_uncertainty_mm`` comes from when not from the station file (the simulator's CMM)."""


def signoff_from_station(station: Any, path: str | Path | None) -> SignoffSettings:
    """The sign-off settings of a validated ``StationConfig`` (a laser tracker's identity, MPE and calibration come
    from its ``[tracker]`` section when the certificate is made: ``procedures.certificate``)."""
    cmm = {} if station.cmm is None else {k: getattr(station.cmm, k) for k in CmmIdentity.model_fields}
    return SignoffSettings(name=station.name, operator=station.operator, machine_serial=station.machine.serial,
                           acceptance=station.acceptance, cmm=CmmIdentity(**cmm),
                           station_file=None if path is None else str(path))


def sim_signoff(file: SignoffSettings, station: Any, station_file_given: bool) -> SignoffSettings:
    """The sign-off of a ``--sim`` run: the station file's settings where it gives them, else the simulated
    station's (its CMM's identity and stated uncertainty from the simulator, its example limits).

    A station file replaces the example limits as a whole (its [acceptance], or none); the CMM's identity and
    uncertainty fall back to the simulator's one by one.
    """
    sim_cmm = {k: None if station.cmm is None else getattr(station.cmm, k) for k in CmmIdentity.model_fields}
    cmm = {k: v if (v := getattr(file.cmm, k)) is not None else sim_cmm[k] for k in CmmIdentity.model_fields}
    from_sim = file.cmm.stated_uncertainty_mm is None and cmm["stated_uncertainty_mm"] is not None
    return file.model_copy(update={
        "cmm": CmmIdentity(**cmm),
        "acceptance": file.acceptance if station_file_given else station.acceptance,
        "cmm_uncertainty_source": "the simulator's [cmm] stated_uncertainty_mm (default 2 x its touch-point "
                                  "noise_sigma_mm)" if from_sim else None})


def load_signoff(path: str | Path | None) -> SignoffSettings:
    """Only the sign-off settings of a station file (for ``--sim``, whose devices come from the simulator).

    None: no station file, nothing set. SignoffFileError naming the field if they are bad.
    """
    if path is None:
        return SignoffSettings()
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except OSError as err:
        raise SignoffFileError(f"station file {p}: cannot read: {err.strerror}") from None
    except tomllib.TOMLDecodeError as err:
        raise SignoffFileError(f"station file {p}: not valid TOML: {err}") from None
    cmm = data.get("cmm") if isinstance(data.get("cmm"), dict) else {}
    machine = data.get("machine") if isinstance(data.get("machine"), dict) else {}
    try:
        return SignoffSettings.model_validate({
            "name": data.get("name"), "operator": data.get("operator"), "machine_serial": machine.get("serial"),
            "acceptance": data.get("acceptance", {}), "station_file": str(p),
            "cmm": {k: cmm[k] for k in CmmIdentity.model_fields if k in cmm}})
    except ValidationError as err:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])).replace('machine_serial', 'machine.serial')}: "
                             f"{e['msg'].removeprefix('Value error, ')}" for e in err.errors())
        raise SignoffFileError(f"station file {p}: {problems}") from None
