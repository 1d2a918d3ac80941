"""The servo controller: the abstract interface and its errors (``base``), one module per protocol (``hilcal_can``:
hilcal's own CAN message set; ``modbus``: the parameter interface over Modbus; CANopen: ``canopen_motion`` and
``canopen_params`` on ``canopen_link``, configured by ``canopen_mapping`` resolved against the EDS in
``canopen_resolved``, with CiA 301's codes in words in ``canopen_codes``), the CAN frames (``can_codec``), the SLCAN
adapter (``slcan_bus``) and the parameter sets and audit records an upload carries (``parameter_sets``).

The names below load on first use (lazy_loader), so a module that needs only the parameter sets does not import
python-can, cantools or pymodbus.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "base": ["ControllerError", "ControllerFault", "ControllerInterface", "ControllerLost", "Feedback",
             "ParameterInterface"],
    "canopen_mapping": ["CanopenMapping", "MappingError"],
    "canopen_motion": ["CanopenController"],
    "canopen_params": ["CanopenParams"],
    "hilcal_can": ["ControllerCan"],
    "modbus": ["ControllerParams"],
    "parameter_sets": ["CompensationBlock", "Identity", "ParameterSet", "UploadRecord", "WriteRecord"],
})
