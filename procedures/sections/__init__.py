"""Sections of a station file with a room of their own: ``controller`` (``[controller]``: the protocol, a CANopen
device's EDS, node ids and mapping) and ``tracker`` (``[instrument]`` and a laser tracker's ``[tracker]``).
``procedures.station`` reads the whole file."""
