"""Missing-physics discovery: what the geometric model leaves out of a recording, named, located and modelled.

``diagnose`` (in ``search``) is the entry point: it fits the geometry, tests candidate effects from the library
(``physics``, on the per-leg variables of ``context``) and generic shapes no library lists (``generic_terms``,
grouped by ``term_groups``), measures the residual against a noise yardstick (``noise``), selects groups by
held-out evidence (``regression``, ``selection``), describes the rest (``shapes``, ``findings``), proposes poses
that would separate what the recording cannot (``augmentation``) and explains the answer in words (``explain``),
returning a ``Diagnosis`` (``result``).

May import the calibration math at the top of ``hilcal`` (robot, recording, kinematics, error models,
identification, metrics, pose measurement, workspace) and itself; never ``hilcal.planning`` or
``hilcal.reports``. A new effect model goes into ``physics`` (see docs/architecture.md).

The names below load on first use (lazy_loader), so importing one light module of the package (``corrections``)
does not import the statistics of the search.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "context": ["EffectContext"],
    "noise": ["NoiseLevel"],
    "result": ["Diagnosis"],
    "search": ["diagnose"],
})
