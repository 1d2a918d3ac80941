"""hilcal: kinematic calibration of 6-6 Gough/Stewart platforms (pure math and data, no device I/O).

The calibration math sits at the top: ``robot`` (robot file), ``kinematics``, ``workspace``, ``error_models``,
``identification``, ``identifiability``, ``metrics``, ``recording`` (CSV format), ``sphere_fit``,
``pose_measurement``, ``compensation`` and ``calibration``. The rooms by job: ``planning/`` (pose designs and
machine time), ``discovery/`` (missing-physics diagnosis), ``importing/`` (recordings from machines' own files),
``reports/`` (run and diagnosis reports) and ``protocols/`` (declarative device protocol definitions). See
docs/architecture.md.
"""

__version__ = "0.1.0"
