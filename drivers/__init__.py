"""Device drivers (protocol adapters), one room per device as python-can has ``interfaces/``: ``cmm/`` (the
coordinate measuring machine), ``tracker/`` (the laser tracker) and ``controller/`` (the servo controller);
``instrument`` puts the CMM and the tracker behind the one interface the run measures with."""
