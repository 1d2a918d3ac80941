"""The simulated rig's truth physics, checked against constructions made independently in the tests."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from hilcal.robot import default_robot, rotation_matrix
from sim_devices.rig.config import (
    PAPER_ERRORS_FILE,
    CmmPose,
    GeometryErrors,
    LegErrors,
    RigConfig,
    load_errors,
    random_errors,
)
from sim_devices.rig.rig import SimulatedRig, _pose_from_rotation, _rotation_from_pose
from sim_devices.rotation import matrix_from_rpy_deg, rpy_deg_from_matrix

ROBOT = default_robot()

# The paper's Table 2 (da_x, da_y, da_z, db_x, db_y, db_z, dl_x, dl_y, dl_z), retyped here from the article.
PAPER_TABLE2 = np.array(
    [
        [0.90, -0.09, 0.84, -0.18, -0.72, -0.97, 0.69, 0.36, -0.39],
        [-0.54, -0.96, 0.48, 0.79, -0.59, 0.49, 0.05, -0.24, -0.62],
        [0.21, 0.64, -0.65, -0.88, -0.60, -0.11, -0.59, 0.66, -0.61],
        [-0.03, -0.11, -0.19, -0.29, 0.21, 0.86, 0.34, 0.05, 0.36],
        [0.78, 0.23, 0.87, 0.63, -0.46, -0.07, 0.68, 0.42, -0.39],
        [0.52, 0.58, 0.83, -0.98, -0.61, -0.16, -0.96, -0.14, 0.08],
    ]
)
# The leg vectors l_i at the home pose, Table 1 of the paper (mm).
PAPER_LEG_VECTORS = np.array(
    [
        [-654.6, -2916.5, 3091.2],
        [-2198.5, -2025.2, 3091.2],
        [2853.1, 891.3, 3091.2],
        [2853.1, -891.3, 3091.2],
        [-2198.5, 2025.2, 3091.2],
        [-654.6, 2916.5, 3091.2],
    ]
)


def random_poses(n: int, seed: int) -> np.ndarray:
    lo, hi = ROBOT.workspace.T
    return np.random.default_rng(seed).uniform(lo, hi, (n, 6))


def ik_lengths(pose: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|R a_i + t - b_i| with hilcal.robot's rotation_matrix (not the rig's own rotations)."""
    R = rotation_matrix(np.radians(pose[3:]))
    return np.linalg.norm(a @ R.T + pose[:3] - b, axis=1)


def test_rig_euler_convention_matches_robot_rotation_matrix() -> None:
    rng = np.random.default_rng(3)
    for rpy_deg in rng.uniform([-80, -80, -179], [80, 80, 179], (50, 3)):
        ours = rotation_matrix(np.radians(rpy_deg))
        np.testing.assert_allclose(matrix_from_rpy_deg(rpy_deg), ours, atol=1e-14)
        np.testing.assert_allclose(rpy_deg_from_matrix(ours), rpy_deg, atol=1e-9)


def test_controller_ik_uses_nominal_geometry_and_quantizes() -> None:
    rig = SimulatedRig(ROBOT, RigConfig(errors=load_errors("table5"), leg_resolution_mm=0.01))
    for pose in random_poses(20, 1):
        L = rig.controller_ik(pose)
        np.testing.assert_allclose(L, ik_lengths(pose, ROBOT.a, ROBOT.b), atol=0.005 + 1e-9)
        np.testing.assert_allclose(L / 0.01, np.round(L / 0.01), atol=1e-6)
    batch = random_poses(5, 2)
    np.testing.assert_array_equal(rig.controller_ik(batch), np.array([rig.controller_ik(p) for p in batch]))


def test_zero_errors_fk_returns_the_commanded_pose() -> None:
    rig = SimulatedRig(ROBOT, RigConfig(errors=load_errors("zero"), leg_resolution_mm=0.0))
    for pose in random_poses(30, 4):
        rig.move_to_lengths(rig.controller_ik(pose))
        got = rig.true_pose()
        assert np.max(np.abs(got[:3] - pose[:3])) < 1e-6
        assert np.max(np.abs(got[3:] - pose[3:])) < 1e-8


def test_fk_satisfies_true_leg_equations() -> None:
    da, db = PAPER_TABLE2[:, 0:3], PAPER_TABLE2[:, 3:6]
    dl0 = np.einsum("ij,ij->i", PAPER_LEG_VECTORS, PAPER_TABLE2[:, 6:9]) / np.linalg.norm(
        PAPER_LEG_VECTORS, axis=1
    )
    rig = SimulatedRig(ROBOT, RigConfig(errors=load_errors("table2")))
    poses = random_poses(40, 5)
    lengths = rig.controller_ik(poses)
    true_poses = rig.true_poses_for_lengths(lengths)
    worst_pose_error = 0.0
    for pose, L, true in zip(poses, lengths, true_poses, strict=True):
        residual = ik_lengths(true, ROBOT.a + da, ROBOT.b + db) - (L + dl0)
        assert np.max(np.abs(residual)) < 1e-9
        worst_pose_error = max(worst_pose_error, float(np.max(np.abs(true[:3] - pose[:3]))))
    assert 0.1 < worst_pose_error < 20.0  # errors of ~1 mm move the platform by mm, not by metres


def test_true_pose_follows_moves_with_warm_start() -> None:
    rig = SimulatedRig(ROBOT, RigConfig(errors=load_errors("table5")))
    lengths = rig.controller_ik(random_poses(10, 6))
    expected = rig.true_poses_for_lengths(lengths)
    for L, want in zip(lengths, expected, strict=True):
        rig.move_to_lengths(L)
        np.testing.assert_array_equal(rig.reported_lengths(), L)
        np.testing.assert_allclose(rig.true_pose(), want, atol=1e-9)


def test_move_rejects_lengths_outside_limits() -> None:
    rig = SimulatedRig(ROBOT, RigConfig(errors=load_errors("zero")))
    lo, hi = ROBOT.leg_limits
    bad = np.full(6, 4300.0)
    bad[3] = hi + 1.0
    with pytest.raises(ValueError, match="leg 4"):
        rig.move_to_lengths(bad)
    bad[3] = lo - 1.0
    with pytest.raises(ValueError, match="leg 4"):
        rig.move_to_lengths(bad)
    with pytest.raises(ValueError, match="shape"):
        rig.move_to_lengths(np.full(5, 4300.0))


# ---------------------------------------------------------------- paper tables and the dl0 mapping


def test_paper_tables_spot_checks() -> None:
    with open(PAPER_ERRORS_FILE, "rb") as fh:
        raw = tomllib.load(fh)
    assert raw["table2"]["legs"][0]["da_mm"][0] == 0.90
    assert raw["table5"]["legs"][5]["dl_mm"][2] == -0.8479
    assert raw["table3"]["legs"][1]["da_mm"] == [0.2769, -0.1350, 0.3035]
    assert raw["table4"]["legs"][4]["db_mm"] == [0.8176, -0.2109, 0.0592]
    assert raw["table5"]["legs"][1]["db_mm"][0] == 2.9080
    assert raw["table3"]["legs"][0]["dl_mm"] == [-0.0434, 0.0343, 0.3578]
    table2 = np.array([[*leg["da_mm"], *leg["db_mm"], *leg["dl_mm"]] for leg in raw["table2"]["legs"]])
    np.testing.assert_array_equal(table2, PAPER_TABLE2)
    da, db, _ = load_errors("table2").as_arrays()
    np.testing.assert_array_equal(da, PAPER_TABLE2[:, 0:3])
    np.testing.assert_array_equal(db, PAPER_TABLE2[:, 3:6])


def test_dl0_is_the_leg_vector_error_projected_on_the_home_leg_direction() -> None:
    with open(PAPER_ERRORS_FILE, "rb") as fh:
        raw = tomllib.load(fh)
    for name in ("table2", "table3", "table4", "table5"):
        dl = np.array([leg["dl_mm"] for leg in raw[name]["legs"]])
        expected = [
            float(np.dot(v, d)) / float(np.sqrt(np.dot(v, v)))
            for v, d in zip(PAPER_LEG_VECTORS, dl, strict=True)
        ]
        np.testing.assert_allclose(load_errors(name).as_arrays()[2], expected, atol=1e-12)
    assert load_errors("table2").as_arrays()[2][0] == pytest.approx(
        (-654.6 * 0.69 - 2916.5 * 0.36 - 3091.2 * 0.39) / np.sqrt(654.6**2 + 2916.5**2 + 3091.2**2), abs=1e-12
    )


def test_errors_file_with_scalar_or_vector_length_errors(tmp_path: Path) -> None:
    lines = []
    for i in range(6):
        lines += ["[[legs]]", f"da_mm = [{i}.0, 0.5, -0.5]", "db_mm = [0.0, 0.0, 0.25]"]
        lines.append(f"dl0_mm = {0.1 * i}" if i % 2 == 0 else "dl_mm = [0.0, 0.0, 1.0]")
    path = tmp_path / "errors.toml"
    path.write_text("\n".join(lines) + "\n")
    da, db, dl0 = load_errors(path).as_arrays()
    np.testing.assert_array_equal(da[:, 0], np.arange(6.0))
    np.testing.assert_array_equal(db[:, 2], np.full(6, 0.25))
    assert dl0[0] == 0.0 and dl0[2] == pytest.approx(0.2) and dl0[4] == pytest.approx(0.4)
    cos_leg_to_z = 3091.2 / np.linalg.norm(PAPER_LEG_VECTORS, axis=1)
    np.testing.assert_allclose(dl0[[1, 3, 5]], cos_leg_to_z[[1, 3, 5]], atol=1e-5)
    bad = tmp_path / "bad.toml"
    bad.write_text("[[legs]]\nda_mm = [0, 0, 0]\n")
    with pytest.raises(ValueError, match="exactly 6"):
        load_errors(bad)
    with pytest.raises(ValueError, match="not a built-in set"):
        load_errors(tmp_path / "nope.toml")


def test_error_vector_order_and_random_errors() -> None:
    legs = [
        LegErrors(da_mm=[i + 0.1, i + 0.2, i + 0.3], db_mm=[i + 0.4, i + 0.5, i + 0.6], dl0_mm=i + 0.7)
        for i in range(6)
    ]
    vec = GeometryErrors(legs=legs).to_vector()
    np.testing.assert_allclose(vec, [i + 0.1 * (k + 1) for i in range(6) for k in range(7)])
    assert GeometryErrors.from_vector(vec) == GeometryErrors(legs=legs)
    e1, e2 = random_errors(11, 0.5), random_errors(11, 0.5)
    assert e1 == e2 and e1 != random_errors(12, 0.5)
    assert 0.3 < np.std(e1.to_vector()) < 0.7
    with pytest.raises(ValueError):
        GeometryErrors(legs=legs[:5])
    with pytest.raises(ValueError):
        LegErrors(da_mm=[0.0, 0.0], db_mm=[0.0, 0.0, 0.0])


# ---------------------------------------------------------------- CMM


def test_sphere_noise_statistics_and_cmm_frame() -> None:
    sigma = 0.01
    cmm = CmmPose(x_mm=2500.0, y_mm=-1800.0, z_mm=-400.0, roll_deg=2.0, pitch_deg=-1.5, yaw_deg=135.0)
    rig = SimulatedRig(
        ROBOT, RigConfig(seed=9, errors=load_errors("table4"), cmm_noise_mm=sigma, cmm_pose=cmm)
    )
    rig.move_to_lengths(rig.controller_ik(np.array([50.0, -30.0, 3150.0, 2.0, -3.0, 4.0])))
    pose = rig.true_pose()
    samples = [rig.measure_spheres() for _ in range(2000)]
    platform = np.array([s[0] for s in samples])
    base = np.array([s[1] for s in samples])
    # noise-free sphere centres, built here from rotation_matrix and the CMM placement p_base = Rc p_cmm + tc
    Rc = rotation_matrix(np.radians([2.0, -1.5, 135.0]))
    tc = np.array([2500.0, -1800.0, -400.0])
    R = rotation_matrix(np.radians(pose[3:]))
    platform_true = (ROBOT.platform_spheres @ R.T + pose[:3] - tc) @ Rc
    base_true = (ROBOT.base_spheres - tc) @ Rc
    for measured, truth in ((platform, platform_true), (base, base_true)):
        noise = measured - truth
        assert np.max(np.abs(noise.mean(axis=0))) < 5 * sigma / np.sqrt(2000)
        per_coordinate_std = noise.std(axis=0, ddof=1)
        assert np.all(np.abs(per_coordinate_std / sigma - 1) < 0.1)


def test_seeded_reproducibility() -> None:
    cfg = RigConfig(seed=21, errors=load_errors("table3"))
    assert RigConfig(seed=21, errors=load_errors("table3")).cmm_pose == cfg.cmm_pose
    assert RigConfig(seed=22, errors=load_errors("table3")).cmm_pose != cfg.cmm_pose
    assert 0.0 <= cfg.cmm_pose.yaw_deg < 360.0
    assert abs(cfg.cmm_pose.roll_deg) < 10 and abs(cfg.cmm_pose.pitch_deg) < 10
    runs = []
    for config in (
        cfg,
        RigConfig(seed=21, errors=load_errors("table3")),
        RigConfig(seed=22, errors=load_errors("table3"), cmm_pose=cfg.cmm_pose),
    ):
        rig = SimulatedRig(ROBOT, config)
        out = []
        for pose in random_poses(3, 8):
            rig.move_to_lengths(rig.controller_ik(pose))
            out.append(np.concatenate(rig.measure_spheres()))
        runs.append(np.array(out))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.array_equal(runs[0], runs[2])
    np.testing.assert_allclose(runs[0], runs[2], atol=0.1)  # same truth, different noise


def test_levenberg_marquardt_fallback_finds_the_newton_pose_from_a_far_start() -> None:
    """The rare FK fallback (scipy imported when it runs) lands on the pose Newton finds from a warm start."""
    rig = SimulatedRig(ROBOT, RigConfig(errors=load_errors("table5"), seed=3))
    rig.move_to_lengths(rig.controller_ik(ROBOT.home + np.array([50.0, -30.0, 20.0, 3.0, -2.0, 5.0])))
    pose = rig.true_pose()
    far_start = _rotation_from_pose(ROBOT.home + np.array([0.0, 0.0, 0.0, 10.0, -10.0, 20.0]))
    target = rig.true_lengths(rig.reported_lengths())
    R, t = rig._solve_fk_lm(target, far_start, ROBOT.home[:3], rig.reported_lengths())
    np.testing.assert_allclose(_pose_from_rotation(R, t), pose, rtol=0, atol=1e-9)
