"""The simulated coordinate measuring machine, speaking I++ DME 1.4.3: its command reader (``wire``, ``methods``),
sessions and transactions (``session``, ``handlers``, ``responses``), machine and stylus-ball physics (``machine``,
``physics``, ``tools``), fault injection (``faults``, ``config``) and the server on a pseudo-terminal or TCP
(``server``). See docs/cmm_simulator.md.

May import ``hilcal.protocols``, ``hilcal.robot``, ``sim_devices.rig``, ``sim_devices.config_base``,
``sim_devices.rotation`` and itself; never ``drivers`` or the controller.
"""

from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.cmm.session import CmmSession

__all__ = ["CmmServerConfig", "CmmServerHandle", "CmmSession", "start_cmm_server"]
