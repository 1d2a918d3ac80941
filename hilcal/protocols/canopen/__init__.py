"""CANopen electronic data sheets (CiA 306 EDS files) that the CANopen driver and the simulated devices share.

``HEXAPOD_CONTROLLER_EDS``: the HX-6, one node for a whole hydraulic hexapod (CiA 301, CiA 402 device control,
manufacturer-specific objects for legs, geometry and compensation). ``CIA402_LEG_DRIVE_EDS``: the LD-1, a CiA 402
servo drive per leg of an electric hexapod. Each file's [Comments] section states its units and behaviour.
"""

from __future__ import annotations

from pathlib import Path

EDS_DIR = Path(__file__).resolve().parent
HEXAPOD_CONTROLLER_EDS = EDS_DIR / "hexapod_controller.eds"
CIA402_LEG_DRIVE_EDS = EDS_DIR / "cia402_leg_drive.eds"

__all__ = ["CIA402_LEG_DRIVE_EDS", "EDS_DIR", "HEXAPOD_CONTROLLER_EDS"]
