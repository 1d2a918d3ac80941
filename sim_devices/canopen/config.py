"""What makes the simulated CANopen devices: the node id of the HX-6 hexapod controller and those of the six LD-1
leg drives (validated, frozen). Servo, rig and fault settings are the controller model's (``ControllerSimConfig``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

Variant = Literal["hexapod", "cia402"]


class CanopenSimConfig(BaseModel):
    """Node ids on the simulated CANopen bus."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    node_id: int = Field(default=1, ge=1, le=127, description="node id of the HX-6 hexapod controller")
    drive_node_ids: list[int] = Field(default_factory=lambda: [1, 2, 3, 4, 5, 6], min_length=6, max_length=6,
                                      description="node ids of the LD-1 drives of legs 1-6 (CiA 402 variant)")

    @model_validator(mode="after")
    def _distinct_ids(self) -> CanopenSimConfig:
        ids = self.drive_node_ids
        if any(not 1 <= i <= 127 for i in ids) or len(set(ids)) != len(ids):
            raise ValueError(f"drive_node_ids must be six distinct node ids 1..127, got {ids}")
        return self

    def node_ids(self, variant: Variant) -> list[int]:
        return [self.node_id] if variant == "hexapod" else list(self.drive_node_ids)
