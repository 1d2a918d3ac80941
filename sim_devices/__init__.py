"""Simulated devices: an independent physical model of the rig, its controller and its CMM.

Rooms: ``rig/`` (truth physics and its configuration), ``controller/`` (the servo controller's state machine and
its CAN and Modbus servers), ``cmm/`` (the CMM session and server). At the top, the composition:
``simulator`` (everything in one process, ``start_sim``), ``sim_config`` and ``sim_state`` (the ``hilcal sim``
TOML and the persistent state), ``launcher`` (the process), ``config_base`` and ``rotation`` (numpy rotation helpers).
The simulators share with ``hilcal`` only the robot file, the protocol definitions and the recording format, never
the models it fits.
"""
