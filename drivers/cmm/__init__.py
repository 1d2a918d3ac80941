"""The coordinate measuring machine: the abstract interface (``base``), the probing strategy that is the same on
every transport (``probing``), results and errors (``types``), and the I++ DME 1.4.3 driver (``ippdme``) on its
transaction layer (``link``), line syntax (``wire``), response checks (``forms``), answer readers (``answers``) and
transcript (``transcript``).

The names below load on first use (lazy_loader), so a module that needs only the results does not import pyserial.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "base": ["CmmInterface"],
    "ippdme": ["IppDmeCmm", "IppDmeConfig"],
    "transcript": ["TRANSCRIPT_NAME", "TranscriptFile", "TranscriptMemory"],
    "types": ["CmmCollision", "CmmConnectionError", "CmmDriverError", "CmmEmergencyStop", "CmmError",
              "CmmInErrorState", "CmmMotionTimeout", "CmmProtocolError", "CmmTimeout", "CmmToolChanged",
              "CmmTransactionAborted", "PoseMeasurement", "PoseMeasurementError", "ProbeLost", "ProbeMiss",
              "ProbeRecord", "ProbeStatus", "ProbingConfig", "SphereMeasurement", "SphereMeasurementError",
              "SphereSearch", "Touch", "TouchSettings"],
})
