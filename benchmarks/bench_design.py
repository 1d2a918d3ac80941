"""Benchmark of measurement-pose design: run time and D-efficiency against 32 random poses.

Run ``python benchmarks/bench_design.py``; ``run()`` returns the figures as a dict (medians over seeds).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from hilcal.planning import design as D
from hilcal.robot import Robot, default_robot

SEEDS = (0, 1, 2)


def _cases(robot: Robot) -> dict[str, Callable[[np.random.Generator], D.Design]]:
    return {
        "coordinate_exchange32": lambda rng: D.coordinate_exchange(robot, 32, rng),
        "coordinate_exchange64": lambda rng: D.coordinate_exchange(robot, 64, rng),
        "factorial_exchange32": lambda rng: D.factorial_exchange(robot, 32, rng),
    }


def run(robot: Robot | None = None, seeds: tuple[int, ...] = SEEDS) -> dict[str, dict[str, float]]:
    """Median time (s), D-efficiency vs 32 random poses, scaled condition number and passes per design."""
    robot = robot or default_robot()
    raw: dict[str, dict[str, list[float]]] = {}
    for seed in seeds:
        random_rng, design_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2))
        random32 = D.random_poses(robot, 32, random_rng)
        ref = D.design_metrics(robot, random32).log_det
        rows = {"random32": (0.0, random32, 0)}
        for name, make in _cases(robot).items():
            t0 = time.perf_counter()
            design = make(design_rng)
            rows[name] = (time.perf_counter() - t0, design.poses, design.n_passes)
        for name, (seconds, poses, passes) in rows.items():
            m = D.design_metrics(robot, poses, reference_log_det_per_pose=ref)
            entry = raw.setdefault(
                name, {"time_s": [], "d_efficiency": [], "condition_number": [], "passes": []}
            )
            entry["time_s"].append(seconds)
            entry["d_efficiency"].append(m.d_efficiency)
            entry["condition_number"].append(m.condition_number)
            entry["passes"].append(passes)
    return {name: {k: float(np.median(v)) for k, v in entry.items()} for name, entry in raw.items()}


def markdown(results: dict[str, dict[str, float]]) -> str:
    """The results as a Markdown table."""
    lines = [
        "| design | time (s) | passes | D-eff vs random32 | cond (scaled) |",
        "|---|---:|---:|---:|---:|",
    ]
    for name, r in results.items():
        lines.append(
            f"| {name} | {r['time_s']:.2f} | {r['passes']:.0f} | {r['d_efficiency']:.3f} "
            f"| {r['condition_number']:.0f} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    print(f"medians over seeds {SEEDS}, robot {default_robot().name}\n")
    print(markdown(run()))
