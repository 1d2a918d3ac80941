"""The coordinate measuring machine: the abstract interface (``base``), the probing strategy that is the same on
every transport (``probing``), results and errors (``types``) and the transport (``serial``).

The names below load on first use (lazy_loader), so a module that needs only the results does not import pyserial.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "base": ["CmmInterface"],
    "serial": ["SerialCmm", "SerialCmmConfig"],
    "types": ["CmmConnectionError", "CmmDriverError", "CmmError", "CmmProtocolError", "CmmTimeout", "PoseMeasurement",
              "PoseMeasurementError", "ProbeMiss", "ProbeRecord", "ProbeStatus", "ProbingConfig", "SphereMeasurement",
              "SphereMeasurementError", "SphereSearch"],
})
