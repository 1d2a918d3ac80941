"""The simulated CANopen controller: the controller model (``model``, the simulator's servo, rig and compensation
arithmetic with a CANopen device's parameter memory) as the HX-6 hexapod controller (``hexapod_node``) or as six
CiA 402 LD-1 leg drives (``leg_drives``), each a canopen ``LocalNode`` with its object dictionary from the shared EDS
(``hilcal/protocols/canopen/``) and NMT, heartbeat, EMCY, PDOs (``pdo``) and store/restore (``nvram``) run by
``node``; ``cia402`` is the device control state machine. ``bus`` carries the nodes over the SLCAN server on a pty or
a python-can bus; ``servers`` starts them.

May import ``hilcal.protocols``, ``hilcal.robot``, ``sim_devices.controller``, ``sim_devices.rig``,
``sim_devices.sim_state`` and itself; never ``drivers`` or ``procedures``. The names below load on first use
(lazy_loader), so the simulator configuration can name the CANopen settings without importing the devices.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "config": ["CanopenSimConfig"],
    "model": ["CanopenController"],
    "servers": ["CanopenServers", "serve_canopen"],
})
