"""The acceptance test evaluated: ISO 9283 AP and RP per test pose with their uncertainties, and the figures that
the station's limits are checked against.

Pure: the caller hands over the commanded test poses, the attained (measured) poses in visiting order with the test
pose each belongs to, and the CMM's pose covariance; the result objects carry their JSON form for report.json.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hilcal.acceptance.iso9283 import POSE_NAMES, PoseCharacteristics, pose_characteristics
from hilcal.acceptance.uncertainty import Figure, ap_figures, rp_figures


@dataclass(frozen=True)
class IsoPoseResult:
    """AP and RP of one test pose (ISO 9283), each with its uncertainty."""

    name: str
    characteristics: PoseCharacteristics
    ap: dict[str, Figure]
    """ap_p_mm, ap_a_deg, ap_b_deg, ap_c_deg."""
    rp: dict[str, Figure]
    """rp_l_mm, rp_a_deg, rp_b_deg, rp_c_deg."""

    def as_json(self) -> dict[str, object]:
        ch = self.characteristics
        return {
            "pose": self.name, "commanded": ch.commanded.tolist(), "n_cycles": ch.n_cycles,
            "barycentre": ch.barycentre.tolist(),
            "ap_x_mm": float(ch.ap_xyz_mm[0]), "ap_y_mm": float(ch.ap_xyz_mm[1]), "ap_z_mm": float(ch.ap_xyz_mm[2]),
            **{k: f.as_json() for k, f in self.ap.items()},
            "l_mean_mm": ch.l_mean_mm, "s_l_mm": ch.s_l_mm,
            "s_a_deg": float(ch.s_abc_deg[0]), "s_b_deg": float(ch.s_abc_deg[1]), "s_c_deg": float(ch.s_abc_deg[2]),
            **{k: f.as_json() for k, f in self.rp.items()},
        }


def evaluate_iso9283(poses: np.ndarray, attained: np.ndarray, which: np.ndarray, cmm_cov: np.ndarray | None, *,
                     seed: int = 0) -> list[IsoPoseResult]:
    """AP and RP of each test pose with at least two attained poses; `which[j]` is the test pose of row j (0 = P1)."""
    P = np.asarray(poses, dtype=float).reshape(-1, 6)
    q = np.asarray(attained, dtype=float).reshape(-1, 6)
    w = np.asarray(which, dtype=int).ravel()
    if len(q) != len(w):
        raise ValueError(f"{len(q)} attained poses but {len(w)} test-pose labels")
    results = []
    for k, commanded in enumerate(P):
        rows = q[w == k]
        if len(rows) < 2:
            continue
        results.append(IsoPoseResult(POSE_NAMES[k] if k < len(POSE_NAMES) else f"P{k + 1}",
                                     pose_characteristics(rows, commanded),
                                     ap_figures(rows, commanded, cmm_cov, seed=seed + k),
                                     rp_figures(rows, seed=seed + 100 + k)))
    return results


def _abs(f: Figure) -> Figure:
    return Figure(abs(f.value), f.u, f.unit)


def limit_figures(after: Mapping[str, Figure] | None, iso: list[IsoPoseResult]) -> dict[str, list[tuple[str, Figure]]]:
    """What each acceptance limit (``hilcal.acceptance.verdict.LIMITS``) is checked against: (where, figure)."""
    out: dict[str, list[tuple[str, Figure]]] = {}
    if after is not None:
        for key in ("max_position_mm", "rms_position_mm", "max_orientation_deg", "rms_orientation_deg"):
            out[key] = [("verification poses after calibration", after[key])]
    if iso:
        out["ap_position_mm"] = [(r.name, r.ap["ap_p_mm"]) for r in iso]
        out["rp_position_mm"] = [(r.name, r.rp["rp_l_mm"]) for r in iso]
        out["ap_orientation_deg"] = [(f"{r.name} AP_{a}", _abs(r.ap[f"ap_{a}_deg"])) for r in iso for a in "abc"]
        out["rp_orientation_deg"] = [(f"{r.name} RP_{a}", r.rp[f"rp_{a}_deg"]) for r in iso for a in "abc"]
    return out
