"""The laser tracker: the abstract interface and its errors (``base``), Leica's emScon over TCP (``emscon``), a
platform pose from reflectors and monuments (``pose``) and the count of the tracker's stations (``station``).

The names below load on first use (lazy_loader).
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "base": ["Environment", "Reflector", "TrackerConnectionError", "TrackerDriverError", "TrackerError",
             "TrackerInterface", "TrackerPoint", "TrackerTimeout"],
    "emscon": ["EmsconConfig", "EmsconTracker"],
    "pose": ["TargetNotFound", "TrackerPoseConfig", "TrackerPoseMeasurement", "TrackerPoser"],
    "station": ["StationChange", "StationLog"],
})
