"""The simulated tracker as a state machine: units, environment and refraction, reflector, ATR search, beam direction,
lock and measurement; transport-free. ``TrackerMachine.handle`` turns one decoded command into the packets to send,
each after its machine time (``Step``); a refused command raises ``Refused`` with its status.

What it answers (every other command of the AT4xx definitions: ``NotImplemented``):

* ``Initialize``; ``GetTrackerStatus`` (Ready once initialised); ``GoPosition``, ``FindReflector``, ``GetDirection``
  and ``StartMeasurement`` need an initialised tracker (else ``TrackerNotInitialized``).
* ``SetUnits``/``GetUnits`` (every emScon unit; power-up: metre, radian, °C, mbar, %RH, emScon's zero values).
* ``SetEnvironmentParams``/``GetEnvironmentParams`` (power-up 20 °C, 1013.25 hPa, 50 %; outside -20..60 °C,
  500..1200 hPa, 0..100 %: ``MeteoDataOutOfRange``), ``SetRefractionParams``/``GetRefractionParams`` (the indices
  computed from the environment, or set directly until the environment is set again).
* ``GetReflectors`` (one answer per reflector), ``SetReflector``/``GetReflector``; ``SetSearchParams``/
  ``GetSearchParams``; ``SetStationaryModeParams``/``GetStationaryModeParams`` (lMeasTime is the measurement's
  duration); ``SetCoordinateSystemType`` (RHR only)/``GetCoordinateSystemType``; ``SetMeasurementMode`` (Stationary
  only)/``GetMeasurementMode``. A setting that changed is followed by a ``SystemStatusChangeT`` notice.
* ``GoPosition(x, y, z, bUseADM)``: turns the beam towards the point (tracker frame); the lock is lost, and with
  bUseADM the tracker locks on the nearest reflector it sees within the search radius of the point.
* ``FindReflector(d)``: the ATR searches around the point at distance d along the beam and locks on the nearest
  reflector it sees within the search radius (``MeasurementStatusNotReady`` after the search timeout if none).
* ``StartMeasurement``: with a reflector locked (and still in sight: the tracker follows it as the platform moves),
  answers AllOK and, after the measurement time, sends ``SingleMeasResultT``; else ``MeasurementStatusNotReady``.

With ``move_every_poses`` = K the tracker is set up again near its place (``physics.moved_station``, seeded) the
moment its K-th, 2K-th, ... pose is measured: a pose is a round in which every platform reflector (the first
``platform_reflectors``) was measured. Each move is logged (``tracker_sim.moved``, the station before and after).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import structlog

from hilcal.protocols.emscon import (
    AngleUnit,
    Command,
    CoordinateSystemType,
    HumidityUnit,
    LengthUnit,
    MeasMode,
    Packet,
    PressureUnit,
    ResultStatus,
    SingleMeasResultT,
    SystemStatusChange,
    TargetType,
    TemperatureUnit,
    TrackerStatus,
    encode_name,
    new_answer,
    new_error,
    new_status_change,
)
from sim_devices.tracker import physics
from sim_devices.tracker.config import TrackerServerConfig
from sim_devices.tracker.faults import FaultPlan

log = structlog.get_logger(__name__)

REFLECTORS = ((1, "RRR 1.5in", TargetType.RRR15, 19.05), (2, "RRR 0.5in", TargetType.RRR05, 6.35),
              (3, "BRR 1.5in", TargetType.BRR15, 19.05))
"""(id, name, type, surface offset mm) of the reflectors the simulated tracker knows."""
POWER_UP_ENVIRONMENT = (20.0, 1013.25, 50.0)
"""°C, hPa, %RH the tracker corrects for until told otherwise."""
METEO_LIMITS = ((-20.0, 60.0), (500.0, 1200.0), (0.0, 100.0))
INDEX_LIMITS = (1.0, 1.001)
NEEDS_INITIALIZATION = (Command.GoPosition, Command.FindReflector, Command.GetDirection, Command.StartMeasurement)
UNIT_ENUMS = (LengthUnit, AngleUnit, TemperatureUnit, PressureUnit, HumidityUnit)
BEAM_BREAK_AT = 0.4
"""A broken measurement ends this fraction of its time in."""


class Refused(Exception):
    """A command answered with an error status (after ``duration_s`` of machine time)."""

    def __init__(self, status: int, detail: str = "", duration_s: float = 0.0) -> None:
        super().__init__(f"{ResultStatus(status).name}: {detail}")
        self.status = status
        self.detail = detail
        self.duration_s = duration_s


@dataclass
class Step:
    """Packets sent after ``duration_s`` of machine time (before ``time_scale``)."""

    duration_s: float
    packets: list[Packet] = field(default_factory=list)


class TrackerMachine:
    """The tracker's state and physics; shared by every connection (its settings are the tracker's, not a link's)."""

    def __init__(self, config: TrackerServerConfig, reflectors: Callable[[], np.ndarray],
                 platform_reflectors: int = 0) -> None:
        self.config = config
        self.reflectors = reflectors
        """Callable: the reflectors' true centres now, (N, 3) mm in the base frame."""
        self.platform_reflectors = platform_reflectors
        """The first this many reflectors sit on the platform: a round measuring each of them is a pose measured."""
        self.lock = threading.Lock()
        self.R, self.t = physics.station_transform(config.station.as_array())
        self.poses_measured = 0
        self.moves = 0
        """How often the tracker was set up again (``move_every_poses``)."""
        self._round: set[int] = set()
        self._obstacles_base: list[tuple[np.ndarray, float]] = []
        self.obstacles: list[tuple[np.ndarray, float]] = []
        self.set_obstacles([(np.array(o.centre_mm), o.radius_mm) for o in config.obstacles])
        self.units = [0, 0, 0, 0, 0]
        self.environment = POWER_UP_ENVIRONMENT
        self.refraction_set: tuple[float, float] | None = None
        self.reflector_id = REFLECTORS[0][0]
        self.search_radius_mm = config.search_radius_mm
        self.search_timeout_s = config.search_timeout_s
        self.measure_time_s = config.measure_time_s
        self.initialized = False
        self.direction = np.array([1.0, 0.0, 0.0])
        self.locked: int | None = None
        """Index of the reflector the beam is locked on."""
        self.machine_time_s = 0.0
        self.measurements = 0
        self._rng = np.random.default_rng([config.seed, 0x7AC4])

    def set_obstacles(self, obstacles_base: list[tuple[np.ndarray, float]]) -> None:
        """Replace the obstacles (centre in the base frame mm, radius mm)."""
        with self.lock:
            self._obstacles_base = [(np.asarray(c, dtype=float), float(r)) for c, r in obstacles_base]
            self._place_obstacles()

    def _place_obstacles(self) -> None:
        self.obstacles = [(physics.to_tracker(c, self.R, self.t), r) for c, r in self._obstacles_base]

    def station_pose(self) -> np.ndarray:
        """Where the tracker stands now: [x, y, z mm, roll, pitch, yaw deg] of its frame in the base frame."""
        return physics.station_pose(self.R, self.t)

    def place(self, station_pose: np.ndarray) -> None:
        """Set the tracker up at a station [x, y, z mm, roll, pitch, yaw deg] (an operator carrying it; the lock is
        lost). Under the machine's lock."""
        self.R, self.t = physics.station_transform(np.asarray(station_pose, dtype=float))
        self._place_obstacles()
        self.locked = None
        log.info("tracker_sim.placed", station=self.station_pose().round(4).tolist())

    def _count_round(self, index: int) -> None:
        """A platform reflector measured; the round complete (every one of them measured), a pose counted, and after
        every ``move_every_poses`` poses the tracker set up again (the pose's own measurements are all taken)."""
        if index >= self.platform_reflectors:
            return
        self._round.add(index)
        if len(self._round) < self.platform_reflectors:
            return
        self._round.clear()
        self.poses_measured += 1
        every = self.config.move_every_poses
        if every and self.poses_measured % every == 0:
            self._move()

    def _move(self) -> None:
        before = self.station_pose()
        rng = np.random.default_rng([self.config.seed, 0x30E, self.moves])
        self.R, self.t = physics.moved_station(self.R, self.t, self.config.move_mm, self.config.move_deg, rng)
        self._place_obstacles()
        self.locked = None
        self.moves += 1
        log.info("tracker_sim.moved", move=self.moves, after_poses=self.poses_measured,
                 move_mm=self.config.move_mm, move_deg=self.config.move_deg,
                 station_before=before.round(4).tolist(), station_after=self.station_pose().round(4).tolist())

    # ------------------------------------------------------------------ units

    def _to_mm(self, value: float) -> float:
        return value * physics.MM_PER_LENGTH_UNIT[LengthUnit(self.units[0])]

    def _from_mm(self, value_mm: float) -> float:
        return value_mm / physics.MM_PER_LENGTH_UNIT[LengthUnit(self.units[0])]

    def _from_rad(self, value_rad: float) -> float:
        return value_rad / physics.RAD_PER_ANGLE_UNIT[AngleUnit(self.units[1])]

    def _env_out(self) -> tuple[float, float, float]:
        t, p, h = self.environment
        return (physics.from_celsius(t, self.units[2]), p / physics.HPA_PER_PRESSURE_UNIT[PressureUnit(self.units[3])],
                h)

    # ------------------------------------------------------------------ physics

    def targets(self) -> np.ndarray:
        """(N, 3) true reflector centres in the tracker's frame."""
        return physics.to_tracker(np.asarray(self.reflectors(), dtype=float).reshape(-1, 3), self.R, self.t)

    def _seen(self, q: np.ndarray) -> bool:
        d = float(np.linalg.norm(q))
        return self.config.min_range_mm <= d <= self.config.max_range_mm and not physics.blocked(q, self.obstacles)

    def _search(self, centre: np.ndarray, targets: np.ndarray) -> int | None:
        """The nearest reflector in sight within the search radius of ``centre`` (tracker frame)."""
        gaps = np.linalg.norm(targets - centre, axis=1)
        for i in np.argsort(gaps):
            if gaps[i] > self.search_radius_mm:
                return None
            if self._seen(targets[i]):
                return int(i)
        return None

    def indices(self) -> tuple[float, float]:
        """(IFM, ADM) refractive indices the tracker applies."""
        if self.refraction_set is not None:
            return self.refraction_set
        n = physics.refractive_index(*self.environment)
        return n, n

    def sigma_mm(self, distance_mm: float) -> float:
        """Per-axis standard deviation: U(d)/2 (the MPE read as k = 2)."""
        return physics.mpe_mm(distance_mm, self.config.mpe_constant_um, self.config.mpe_per_m_um) / 2.0

    # ------------------------------------------------------------------ commands

    def handle(self, command: int, p: Packet, plan: FaultPlan) -> list[Step]:
        """The steps answering one command (under the machine's lock). Refused for an error status."""
        try:
            name = Command(command).name
        except ValueError:
            raise Refused(ResultStatus.NotImplemented, f"command {command}") from None
        handler = getattr(self, f"_{name}", None)
        if handler is None:
            raise Refused(ResultStatus.NotImplemented, name)
        with self.lock:
            if command in NEEDS_INITIALIZATION and not self.initialized:
                raise Refused(ResultStatus.TrackerNotInitialized, name)
            steps: list[Step] = handler(p, plan) if name == "StartMeasurement" else handler(p)
            return steps

    def _ok(self, command: int, duration_s: float = 0.0, notice: int | None = None, **fields: object) -> list[Step]:
        answer = new_answer(command)
        for key, value in fields.items():
            setattr(answer, key, value)
        packets = [answer] + ([new_status_change(notice)] if notice is not None else [])
        return [Step(duration_s, packets)]

    def _Initialize(self, _p: Packet) -> list[Step]:
        self.initialized = True
        self.locked = None
        return self._ok(Command.Initialize, self.config.initialize_time_s)

    def _GetTrackerStatus(self, _p: Packet) -> list[Step]:
        status = TrackerStatus.Ready if self.initialized else TrackerStatus.NotReady
        return self._ok(Command.GetTrackerStatus, trackerStatus=int(status))

    def _SetUnits(self, p: Packet) -> list[Step]:
        u = p.unitsSettings
        values = [u.lenUnitType, u.angUnitType, u.tempUnitType, u.pressUnitType, u.humUnitType]
        for k, (value, enum) in enumerate(zip(values, UNIT_ENUMS, strict=True)):
            if value not in enum._value2member_map_:
                raise Refused(ResultStatus[f"WrongParameter{k + 1}"], f"{enum.__name__} {value}")
        self.units = [int(v) for v in values]
        return self._ok(Command.SetUnits, notice=SystemStatusChange.UnitsChanged)

    def _GetUnits(self, _p: Packet) -> list[Step]:
        answer = new_answer(Command.GetUnits)
        u = answer.unitsSettings
        u.lenUnitType, u.angUnitType, u.tempUnitType, u.pressUnitType, u.humUnitType = self.units
        return [Step(0.0, [answer])]

    def _SetEnvironmentParams(self, p: Packet) -> list[Step]:
        e = p.environmentData
        env = (physics.to_celsius(e.dTemperature, self.units[2]),
               e.dPressure * physics.HPA_PER_PRESSURE_UNIT[PressureUnit(self.units[3])], e.dHumidity)
        for value, (low, high) in zip(env, METEO_LIMITS, strict=True):
            if not low <= value <= high:
                raise Refused(ResultStatus.MeteoDataOutOfRange, f"{env}")
        self.environment = env
        self.refraction_set = None
        log.info("tracker_sim.environment", temperature_c=env[0], pressure_hpa=env[1], humidity_pct=env[2],
                 adm_index=self.indices()[1])
        return self._ok(Command.SetEnvironmentParams, notice=SystemStatusChange.EnvironmentParamsChanged)

    def _GetEnvironmentParams(self, _p: Packet) -> list[Step]:
        answer = new_answer(Command.GetEnvironmentParams)
        e = answer.environmentData
        e.dTemperature, e.dPressure, e.dHumidity = self._env_out()
        return [Step(0.0, [answer])]

    def _SetRefractionParams(self, p: Packet) -> list[Step]:
        r = p.refractionData
        for k, value in enumerate((r.dIfmRefractionIndex, r.dAdmRefractionIndex)):
            if not INDEX_LIMITS[0] <= value <= INDEX_LIMITS[1]:
                raise Refused(ResultStatus[f"WrongParameter{k + 1}"], f"index {value}")
        self.refraction_set = (float(r.dIfmRefractionIndex), float(r.dAdmRefractionIndex))
        return self._ok(Command.SetRefractionParams, notice=SystemStatusChange.RefractionParamsChanged)

    def _GetRefractionParams(self, _p: Packet) -> list[Step]:
        answer = new_answer(Command.GetRefractionParams)
        answer.refractionData.dIfmRefractionIndex, answer.refractionData.dAdmRefractionIndex = self.indices()
        return [Step(0.0, [answer])]

    def _GetReflectors(self, _p: Packet) -> list[Step]:
        packets = []
        for rid, name, kind, offset_mm in REFLECTORS:
            answer = new_answer(Command.GetReflectors)
            answer.iTotalReflectors, answer.iInternalReflectorId, answer.targetType = len(REFLECTORS), rid, int(kind)
            answer.dSurfaceOffset, answer.cReflectorName = self._from_mm(offset_mm), encode_name(name)
            packets.append(answer)
        return [Step(0.0, packets)]

    def _SetReflector(self, p: Packet) -> list[Step]:
        if p.iInternalReflectorId not in {r[0] for r in REFLECTORS}:
            raise Refused(ResultStatus.WrongParameter1, f"reflector {p.iInternalReflectorId}")
        self.reflector_id = int(p.iInternalReflectorId)
        return self._ok(Command.SetReflector, notice=SystemStatusChange.ReflectorChanged)

    def _GetReflector(self, _p: Packet) -> list[Step]:
        return self._ok(Command.GetReflector, iInternalReflectorId=self.reflector_id)

    def _SetSearchParams(self, p: Packet) -> list[Step]:
        s = p.searchParams
        if not s.dSearchRadius > 0:
            raise Refused(ResultStatus.WrongParameter1, f"radius {s.dSearchRadius}")
        if s.lTimeOut <= 0:
            raise Refused(ResultStatus.WrongParameter2, f"timeout {s.lTimeOut} ms")
        self.search_radius_mm, self.search_timeout_s = self._to_mm(s.dSearchRadius), s.lTimeOut / 1000.0
        return self._ok(Command.SetSearchParams, notice=SystemStatusChange.SearchParamsChanged)

    def _GetSearchParams(self, _p: Packet) -> list[Step]:
        answer = new_answer(Command.GetSearchParams)
        answer.searchParams.dSearchRadius = self._from_mm(self.search_radius_mm)
        answer.searchParams.lTimeOut = round(self.search_timeout_s * 1000.0)
        return [Step(0.0, [answer])]

    def _SetStationaryModeParams(self, p: Packet) -> list[Step]:
        if p.stationaryModeData.lMeasTime <= 0:
            raise Refused(ResultStatus.WrongParameter1, f"lMeasTime {p.stationaryModeData.lMeasTime}")
        self.measure_time_s = p.stationaryModeData.lMeasTime / 1000.0
        return self._ok(Command.SetStationaryModeParams, notice=SystemStatusChange.StationaryModeParamsChanged)

    def _GetStationaryModeParams(self, _p: Packet) -> list[Step]:
        answer = new_answer(Command.GetStationaryModeParams)
        answer.stationaryModeData.lMeasTime, answer.stationaryModeData.bUseADM = round(self.measure_time_s * 1000), 1
        return [Step(0.0, [answer])]

    def _SetCoordinateSystemType(self, p: Packet) -> list[Step]:
        if p.coordSysType != CoordinateSystemType.RHR:
            raise Refused(ResultStatus.NotImplemented, f"coordinate system {p.coordSysType}")
        return self._ok(Command.SetCoordinateSystemType, notice=SystemStatusChange.CoordinateSystemTypeChanged)

    def _GetCoordinateSystemType(self, _p: Packet) -> list[Step]:
        return self._ok(Command.GetCoordinateSystemType, coordSysType=int(CoordinateSystemType.RHR))

    def _SetMeasurementMode(self, p: Packet) -> list[Step]:
        if p.measMode != MeasMode.Stationary:
            raise Refused(ResultStatus.WrongParameter1, f"measurement mode {p.measMode}")
        return self._ok(Command.SetMeasurementMode, notice=SystemStatusChange.MeasurementModeChanged)

    def _GetMeasurementMode(self, _p: Packet) -> list[Step]:
        return self._ok(Command.GetMeasurementMode, measMode=int(MeasMode.Stationary))

    def _turn(self, direction: np.ndarray) -> float:
        """Turn the beam; the time it takes."""
        cos = float(np.clip(self.direction @ direction, -1.0, 1.0))
        self.direction = direction
        return float(np.degrees(np.arccos(cos))) / self.config.slew_speed_deg_s

    def _GoPosition(self, p: Packet) -> list[Step]:
        point = np.array([self._to_mm(v) for v in (p.dVal1, p.dVal2, p.dVal3)])
        if not np.all(np.isfinite(point)) or float(np.linalg.norm(point)) == 0.0:
            raise Refused(ResultStatus.WrongParameter, f"point {point}")
        duration = self._turn(point / np.linalg.norm(point))
        self.locked = self._search(point, self.targets()) if p.bUseADM else None
        log.debug("tracker_sim.go_position", point_mm=point.round(3).tolist(), locked=self.locked)
        return self._ok(Command.GoPosition, duration)

    def _FindReflector(self, p: Packet) -> list[Step]:
        distance = self._to_mm(p.dAproxDistance)
        if not distance > 0:
            raise Refused(ResultStatus.WrongParameter1, f"distance {distance}")
        targets = self.targets()
        found = self._search(self.direction * distance, targets)
        self.locked = found
        if found is None:
            log.info("tracker_sim.not_found", centre_mm=(self.direction * distance).round(3).tolist(),
                     radius_mm=self.search_radius_mm)
            raise Refused(ResultStatus.MeasurementStatusNotReady, "no reflector found", self.search_timeout_s)
        q = targets[found]
        duration = self.config.search_time_s + self._turn(q / np.linalg.norm(q))
        return self._ok(Command.FindReflector, duration)

    def _GetDirection(self, _p: Packet) -> list[Step]:
        _, hz, v = physics.spherical(self.direction)
        return self._ok(Command.GetDirection, dHzAngle=self._from_rad(hz), dVtAngle=self._from_rad(v))

    def _StartMeasurement(self, _p: Packet, plan: FaultPlan) -> list[Step]:
        if self.locked is None:
            raise Refused(ResultStatus.MeasurementStatusNotReady, "no reflector locked")
        q = self.targets()[self.locked]
        if not self._seen(q):
            self.locked = None
            raise Refused(ResultStatus.MeasurementStatusNotReady, "the locked reflector went out of sight")
        self.direction = q / np.linalg.norm(q)
        started = Step(0.0, [new_answer(Command.StartMeasurement)])
        if plan.beam_break:
            self.locked = None
            log.info("tracker_sim.beam_break", reflector=int(np.argmin(np.linalg.norm(self.targets() - q, axis=1))))
            broken = new_error(Command.StartMeasurement, ResultStatus.NoStationaryResult)
            return [started, Step(self.measure_time_s * BEAM_BREAK_AT, [broken])]
        distance = float(np.linalg.norm(q))
        sigma = self.sigma_mm(distance)
        scale = physics.refractive_index(self.config.air.temperature_c, self.config.air.pressure_hpa,
                                         self.config.air.humidity_pct) / self.indices()[1]
        xyz = physics.measure(q, sigma * self.config.noise_scale, scale, self._rng)
        self.measurements += 1
        self._count_round(self.locked)
        result = SingleMeasResultT()
        result.measMode = int(MeasMode.Stationary)
        result.dVal1, result.dVal2, result.dVal3 = (self._from_mm(v) for v in xyz)
        std = self._from_mm(sigma)
        result.dStd1 = result.dStd2 = result.dStd3 = std
        result.dAprioriStd1 = result.dAprioriStd2 = result.dAprioriStd3 = std
        result.dStdTotal = result.dAprioriStdTotal = std * np.sqrt(3.0)
        result.dTemperature, result.dPressure, result.dHumidity = self._env_out()
        return [started, Step(self.measure_time_s, [result])]
