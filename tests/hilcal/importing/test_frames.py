"""Poses logged in an instrument's frame: [frame] align finds the instrument's frame and the target's place on the
platform, and the aligned recording gives the same diagnosis as the recording in the base frame."""

from __future__ import annotations

import csv
import dataclasses
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.discovery.search import diagnose
from hilcal.importing import ImportFileError, import_recording, load_map, parse_hold_out
from hilcal.importing.frames import FrameAlignmentError, align_frames
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.recording import read_recording
from hilcal.robot import load_robot
from hilcal.workspace import random_poses
from tests.hilcal.importing.support import EXAMPLES

LOGGER = EXAMPLES / "logger"
X_POSE = np.array([2480.0, -1310.0, -655.0, 1.5, -2.0, 121.0])
"""A tracker 2.8 m away from the base's origin, turned by 121 deg and tilted by a few degrees."""
Y_POSE = np.array([35.0, -12.0, 48.0, 0.0, 30.0, -15.0])
"""The 6-DoF probe 48 mm above the platform frame, mounted at an angle."""


def _rotation(pose: np.ndarray) -> Rotation:
    return Rotation.from_euler("ZYX", pose[..., 5:2:-1], degrees=True)


def _compose(X: np.ndarray, B: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """X · B · Y for poses [x, y, z mm, roll, pitch, yaw deg] (R = Rz Ry Rx), written with scipy independently."""
    RX, RB, RY = _rotation(X), _rotation(B), _rotation(Y)
    t = RX.apply(RB.apply(Y[:3]) + B[:, :3]) + X[:3]
    yaw_pitch_roll = (RX * RB * RY).as_euler("ZYX", degrees=True)
    return np.column_stack([t, yaw_pitch_roll[:, ::-1]])


@pytest.fixture(scope="module")
def robot():
    return load_robot(LOGGER / "robot.toml")


def test_exact_frames_are_recovered(robot):
    poses = random_poses(robot, 30, np.random.default_rng(3))
    legs = inverse_kinematics(Geometry.nominal(robot), poses)
    fit = align_frames(_compose(X_POSE, poses, Y_POSE), legs, robot)
    np.testing.assert_allclose(fit.base_in_instrument, X_POSE, atol=1e-6)
    np.testing.assert_allclose(fit.target_in_platform, Y_POSE, atol=1e-6)
    np.testing.assert_allclose(fit.apply(_compose(X_POSE, poses, Y_POSE)), poses, atol=1e-6)
    assert fit.rms_position_mm < 1e-6


def test_too_few_rows_or_no_rotation_are_refused(robot):
    poses = random_poses(robot, 30, np.random.default_rng(4))
    legs = inverse_kinematics(Geometry.nominal(robot), poses)
    with pytest.raises(FrameAlignmentError, match="at least 6"):
        align_frames(poses[:4], legs[:4], robot)
    level = poses.copy()
    level[:, 3:] = 0.0
    with pytest.raises(FrameAlignmentError, match="turns by at most"):
        align_frames(level, inverse_kinematics(Geometry.nominal(robot), level), robot)


def _logger_in_tracker_frame(folder, moved_on_day2: np.ndarray | None = None, probe_on_day2: np.ndarray | None = None):
    """The logger example's files with their poses moved into the tracker's frame (quaternions via scipy); with
    moved_on_day2, the tracker stood there on the second day (set up again); with probe_on_day2, the probe was
    mounted there."""
    shutil.copytree(LOGGER, folder)
    for name in ("day1.csv", "day2.csv"):
        tracker = moved_on_day2 if name == "day2.csv" and moved_on_day2 is not None else X_POSE
        probe = probe_on_day2 if name == "day2.csv" and probe_on_day2 is not None else Y_POSE
        path = folder / name
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        pos = np.array([[float(r[f"position_{a}"]) for a in "xyz"] for r in rows])
        quat = np.array([[float(r[f"orientation_{a}"]) for a in "xyzw"] for r in rows])
        ypr = Rotation.from_quat(quat).as_euler("ZYX", degrees=True)
        moved = _compose(tracker, np.column_stack([pos, ypr[:, ::-1]]), probe)
        q = _rotation(moved).as_quat()
        for r, p, qq in zip(rows, moved, q, strict=True):
            r.update({f"position_{a}": f"{v:.5f}" for a, v in zip("xyz", p[:3], strict=True)})
            r.update({f"orientation_{a}": f"{v:.10f}" for a, v in zip("xyzw", qq, strict=True)})
        with path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    return folder


def test_an_unaligned_tracker_log_is_refused_with_a_hint(tmp_path, robot):
    folder = _logger_in_tracker_frame(tmp_path / "logger")
    with pytest.raises(ImportFileError, match=r"outside the robot's workspace.*set \[frame\] align"):
        import_recording([folder / "day1.csv", folder / "day2.csv"], load_map(folder / "map.toml"), robot=robot,
                         hold_out=parse_hold_out("file:day2.csv"))


@pytest.mark.slow
def test_aligned_tracker_log_gives_the_same_diagnosis(tmp_path, robot):
    folder = _logger_in_tracker_frame(tmp_path / "logger")
    (folder / "map.toml").write_text((folder / "map.toml").read_text() + '\n[frame]\nalign = "shared"\n')
    result = import_recording([folder / "day1.csv", folder / "day2.csv"], load_map(folder / "map.toml"), robot=robot,
                              hold_out=parse_hold_out("file:day2.csv"))
    assert any(note.startswith("[frame] aligned (all files)") for note in result.notes)
    lever = float(np.linalg.norm(Y_POSE[:3]))  # 61 mm: the probe's orientation noise acts on it
    assert any(f"the target is {lever:.0f} mm from the platform frame's origin" in note for note in result.notes)
    direct = read_recording(LOGGER / "simulated.csv", robot)
    moved = np.abs(result.recording.meas[:, :3] - direct.meas[:, :3])
    assert moved.max() < 0.5, "the alignment absorbs only the frame-like part of the geometric errors"
    imported, reference = diagnose(result.recording, robot), diagnose(direct, robot)
    assert imported.effects == reference.effects
    for key, value in reference.parameters.items():
        assert abs(imported.parameters[key] - value) <= reference.std_errors[key], key
    assert imported.after is not None and reference.after is not None
    assert imported.after.position_mm.rms == pytest.approx(reference.after.position_mm.rms, rel=0.05)


TRACKER_MOVED = np.array([120.0, 0.0, 0.0, 0.0, 0.0, 3.0])
"""The tracker set up again on day 2: 120 mm away and turned by 3 deg."""


def _import_with_frame(folder, robot, frame: str):
    """Both days imported with the example's map plus a [frame] section (its lines given), day 2 held out."""
    (folder / "frame_map.toml").write_text((folder / "map.toml").read_text() + f"\n[frame]\n{frame}\n")
    return import_recording([folder / "day1.csv", folder / "day2.csv"], load_map(folder / "frame_map.toml"),
                            robot=robot, hold_out=parse_hold_out("file:day2.csv"))


def _assert_base_frame(result, robot) -> None:
    """The aligned poses are the simulator's own (base frame) to well within the geometric errors."""
    direct = read_recording(LOGGER / "simulated.csv", robot)
    assert np.abs(result.recording.meas[:, :3] - direct.meas[:, :3]).max() < 0.5


def test_a_shared_frame_for_a_tracker_set_up_again_is_refused_and_per_file_imports(tmp_path, robot):
    """The tracker moved 120 mm and turned 3 deg between the days: one frame for both cannot fit (the import says
    so and names per_file), a frame per file does."""
    folder = _logger_in_tracker_frame(tmp_path / "logger", X_POSE + TRACKER_MOVED)
    with pytest.raises(ImportFileError, match=r'set up again between the files; set \[frame\] align = "per_file"'):
        _import_with_frame(folder, robot, 'align = "shared"')
    _assert_base_frame(_import_with_frame(folder, robot, 'align = "per_file"'), robot)


def test_a_probe_mounted_anew_needs_its_own_target_place_per_file(tmp_path, robot):
    """per_file fits one target place with every file's tracker frame (the probe stayed on the platform); a probe
    mounted 40 mm elsewhere on day 2 makes that fit far worse than the file's own, which is refused with the key
    to set; target = "per_file" then imports."""
    moved_probe = Y_POSE + np.array([40.0, 0.0, 0.0, 0.0, 0.0, 20.0])
    folder = _logger_in_tracker_frame(tmp_path / "logger", X_POSE + TRACKER_MOVED, moved_probe)
    with pytest.raises(ImportFileError, match=r'mounted anew between the files; set \[frame\] target = "per_file"'):
        _import_with_frame(folder, robot, 'align = "per_file"')
    _assert_base_frame(_import_with_frame(folder, robot, 'align = "per_file"\ntarget = "per_file"'), robot)


def test_align_needs_the_robot_file(tmp_path):
    folder = _logger_in_tracker_frame(tmp_path / "logger")
    (folder / "map.toml").write_text((folder / "map.toml").read_text() + '\n[frame]\nalign = "per_file"\n')
    with pytest.raises(ImportFileError, match="needs the robot file"):
        import_recording([folder / "day1.csv"], load_map(folder / "map.toml"))


@pytest.mark.slow
def test_a_tracker_set_up_anew_each_day_gives_the_planted_zero_shifts(tmp_path, robot):
    """The logger example (re-homed on day 2: legs 2 and 4 read +12 and -9 µm off, make_examples.py) logged by a
    tracker set up again on day 2. With per_file frames each day is a station fitted with the model (the recording's
    station column): the day-2 zero shifts are stated within two standard errors of the planted ones and no leg is
    named shifted that was not. The frames fitted alone with the nominal geometry (the station column dropped) took
    the shifts up and named leg 1 instead, precisely and wrongly. Every fourth row of both days is held out."""
    folder = _logger_in_tracker_frame(tmp_path / "logger", moved_on_day2=TRACKER_MOVED)
    (folder / "frame_map.toml").write_text((folder / "map.toml").read_text() + '\n[frame]\nalign = "per_file"\n')
    result = import_recording([folder / "day1.csv", folder / "day2.csv"], load_map(folder / "frame_map.toml"),
                              robot=robot, hold_out=parse_hold_out("every:4"))
    rec = result.recording
    assert set(np.unique(rec.stations)) == {0, 1}
    assert any("each file is an instrument station" in note for note in result.notes)
    planted_mm = {1: 0.0, 2: 0.012, 3: 0.0, 4: -0.009, 5: 0.0, 6: 0.0}

    def misses(diag) -> list[str]:
        shifts = {n: v for n, v in diag.parameters.items() if "zero_shift" in n}
        assert len(shifts) == 6, diag.explanation
        return [n for n, v in shifts.items() if abs(abs(v) - abs(planted_mm[int(n[3])])) > 2 * diag.std_errors[n]]

    bundled = diagnose(rec, robot)
    assert misses(bundled) == []
    assert not any("reads" in s and "session 2" in s for s in bundled.summary), bundled.summary
    alone = diagnose(dataclasses.replace(rec, extra={k: v for k, v in rec.extra.items() if k != "station"}), robot)
    assert "leg1_zero_shift_session2_mm" in misses(alone)
