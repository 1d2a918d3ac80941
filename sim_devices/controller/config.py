"""What makes one simulated controller: servo speed and tolerances, capabilities (register map 1.1, sensor
readings), identity, transports, the fault injection active from start-up and a dead transducer with the
following-error limit that catches it. Validated (pydantic), frozen."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from hilcal.protocols.controller_states import FaultCode


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class CanFaultConfig(_Strict):
    """CAN fault injection active from start-up (rates are per frame, seeded)."""

    drop_rate: float = Field(default=0.0, ge=0, le=1)
    corrupt_rate: float = Field(default=0.0, ge=0, le=1)
    repeat_rate: float = Field(default=0.0, ge=0, le=1)
    delay_s: float = Field(default=0.0, ge=0, description="extra latency of every controller frame")
    heartbeat: bool = Field(default=True, description="False: the controller sends no Status/Feedback")
    seed: int = 0
    gaps_per_min: float = Field(default=0.0, ge=0, le=600,
                                description="link gaps at random times (Poisson): no controller frame is sent")
    gap_min_s: float = Field(default=0.05, gt=0, le=60, description="shortest gap, s (uniform between min and max)")
    gap_max_s: float = Field(default=0.5, gt=0, le=60, description="longest gap, s")
    gap_log: str | None = Field(default=None, description="JSONL file: every gap, and every frame received in one")
    gap_at_frames: list[int] = Field(default_factory=list, description="also start a gap when the controller has "
                                     "received this many frames (deterministic: the host sends only commands)")
    max_gaps: int | None = Field(default=None, ge=0, description="no gap after this many (counted in gap_log too, "
                                 "so a restarted simulator goes on counting)")

    @model_validator(mode="after")
    def _gap_range(self) -> CanFaultConfig:
        if self.gap_max_s < self.gap_min_s:
            raise ValueError(f"gap_max_s ({self.gap_max_s}) is below gap_min_s ({self.gap_min_s})")
        return self


class ModbusFaultConfig(_Strict):
    """Modbus fault injection active from start-up."""

    drop_after_writes: int | None = Field(
        default=None, ge=1, description="close the connection at this write request (1-based), once"
    )
    execute_dropped_write: bool = Field(
        default=False, description="True: the dropped write is executed before the connection closes"
    )
    exception_code: int | None = Field(default=None, ge=1, le=255, description="answer every request with this")
    response_delay_s: float = Field(default=0.0, ge=0, le=10, description="wait this long before every response")


class ControllerSimConfig(_Strict):
    """Everything that makes one simulated controller."""

    time_scale: float = Field(default=1.0, gt=0, description="simulated seconds per real second")
    leg_speed_mm_s: float = Field(default=50.0, gt=0)
    in_position_tolerance_mm: float = Field(default=0.005, gt=0)
    settle_s: float = Field(default=0.05, ge=0, description="all legs within tolerance this long -> IN_POSITION")
    heartbeat_period_s: float = Field(default=0.02, gt=0, description="real time, not scaled")
    capabilities: Literal["full", "offsets_only"] = "full"
    serial_number: int = Field(default=0x00C0FFEE, ge=0, le=0xFFFFFFFF)
    firmware_version: int = Field(default=0x0102, ge=0, le=0xFFFF)
    device_id: int = Field(default=1, ge=1, le=247)
    initial_fault: FaultCode = FaultCode.NONE
    estop_pressed: bool = False
    slcan_transport: Literal["pty", "tcp"] = "pty"
    modbus_port: int = Field(default=0, ge=0, le=65535, description="0: ephemeral port")
    modbus_rtu: bool = Field(default=False, description="also serve Modbus RTU on a pty")
    can_faults: CanFaultConfig = CanFaultConfig()
    modbus_faults: ModbusFaultConfig = ModbusFaultConfig()
    repeatability_mm: float = Field(default=0.0, ge=0, le=1.0, description="std of each leg's settle error per "
                                    "setpoint that its transducer does not see (the machine's repeatability), mm")
    repeatability_seed: int = Field(default=0, description="seed of the settle errors")
    compensation: bool = Field(default=True, description="register map 1.1: a compensation block (reading scale, "
                               "backlash, compliances, thermal coefficient, stroke table) applied to every setpoint "
                               "and reported length; False: a 1.0 controller with the geometry only")
    force_reading: bool = Field(default=True, description="the controller reads each leg's axial force (pressure "
                                "sensors), so it can apply compliance terms (needs compensation)")
    temperature_reading: bool = Field(default=True, description="the controller reads the leg temperature, so it "
                                      "can apply a thermal coefficient (needs compensation)")
    temperature_filter_s: float = Field(default=60.0, gt=0, description="time constant of the low-pass filter on "
                                        "the temperature the block uses, simulated s")
    dead_transducer_legs: list[int] = Field(default_factory=list, description="legs (1-based) whose length "
                                            "transducer is dead: their reading does not follow the actuator")
    dead_reading_mm: float | None = Field(default=None, ge=0, le=16_777.215, description="the controller length a "
                                          "dead transducer reads (before the compensation block), e.g. 0 for a broken "
                                          "wire; None: it keeps its power-up reading")
    following_error_mm: float = Field(default=5.0, gt=0, description="the servo's following-error limit: a moving "
                                      "leg whose reading is this far from where the ramp has driven its actuator "
                                      "stops the controller (FAULT, FOLLOWING_ERROR)")

    @model_validator(mode="after")
    def _dead_legs(self) -> ControllerSimConfig:
        legs = self.dead_transducer_legs
        if any(not 1 <= leg <= 6 for leg in legs) or len(set(legs)) != len(legs):
            raise ValueError(f"dead_transducer_legs must be distinct legs 1..6, got {legs}")
        return self


