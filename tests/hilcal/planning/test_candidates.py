"""The seeded candidate set of a sequential plan (hilcal.planning.candidates): feasible with the approach margin,
boundary poses on the boundary, the same set for the same seed."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.planning.candidates import boundary_poses, candidate_set, designable_robot
from hilcal.workspace import feasible


def test_candidates_are_feasible_with_the_approach_margin_and_seeded(robot):
    a = candidate_set(robot, 3, n_boundary=100, n_random=100)
    b = candidate_set(robot, 3, n_boundary=100, n_random=100)
    c = candidate_set(robot, 4, n_boundary=100, n_random=100)
    assert np.array_equal(a.poses, b.poses) and not np.array_equal(a.poses, c.poses)
    legs = inverse_kinematics(Geometry.nominal(robot), a.poses)
    assert legs.min() >= robot.leg_limits[0] + 2.0 + 1.0 - 1e-9 and legs.max() <= robot.leg_limits[1]
    assert np.all(feasible(robot, a.poses))
    assert set(a.source) == {"factorial", "boundary", "random"}
    assert a.jacobians.shape == (len(a), 6, 42) and a.library.shape == (len(a), 6, 12)
    # the library columns are each leg's length column times its load, then times its stroke
    np.testing.assert_allclose(a.library[:, :, 0], a.jacobians[:, :, 6] * a.load_kn[:, None, 0])
    np.testing.assert_allclose(a.library[:, :, 11], a.jacobians[:, :, 41] * a.stroke_m[:, None, 5])


def test_boundary_poses_lie_on_the_boundary(robot):
    design = designable_robot(robot, 2.0)
    poses = boundary_poses(design, 50, np.random.default_rng(0))
    assert np.all(feasible(design, poses))
    outward = robot.home + (poses - robot.home) * 1.001
    assert not np.any(feasible(design, outward))


def test_reference_poses_must_be_feasible(robot):
    with pytest.raises(ValueError, match="leave the workspace"):
        candidate_set(robot, 0, n_boundary=10, n_random=10, reference=np.array([[0, 0, 5000.0, 0, 0, 0]]))
