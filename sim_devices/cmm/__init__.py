"""The simulated coordinate measuring machine: its line protocol session (``session``, ``commands``), fault
injection (``faults``, ``config``) and the server on a pseudo-terminal or TCP (``server``).

May import ``hilcal.protocols``, ``hilcal.robot``, ``sim_devices.rig``, ``sim_devices.config_base`` and itself;
never ``drivers`` or the controller.
"""

from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.cmm.session import CmmSession

__all__ = ["CmmServerConfig", "CmmServerHandle", "CmmSession", "start_cmm_server"]
