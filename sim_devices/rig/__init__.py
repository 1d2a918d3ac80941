"""The simulated rig's truth physics: the robot with geometric errors, the library effects, the effects no
library lists and electric legs (motor encoders with homing, drive compliance), written apart from the models that
``hilcal`` fits (``rig``, ``physics``, ``unlisted_physics``, ``electric_physics``), and their configuration
(``config``, ``unlisted_config``, ``unlisted_concealed``, ``electric_config``, with the paper's error tables in
``data/``).

May import ``hilcal.robot``, ``hilcal.protocols``, ``hilcal.recording``, ``sim_devices.config_base``,
``sim_devices.rotation`` and itself; never the controller, the CMM or the composition. A new effect in the rig goes
into ``physics`` (or ``unlisted_physics``) with its switch and parameters in ``config``.
"""

from sim_devices.rig.config import EffectsConfig, GeometryErrors, RigConfig, load_errors, random_errors
from sim_devices.rig.rig import SimulatedRig

__all__ = ["EffectsConfig", "GeometryErrors", "RigConfig", "SimulatedRig", "load_errors", "random_errors"]
