"""Pose ordering: the calibration route that takes the least machine time without confounding drift.

The route is fixed in structure: home, the measure poses, the verify poses, the verify poses again (after
the upload, in the same order), home. Its motion time is a sum of move times (``hilcal.planning.machine_time``:
trapezoidal legs, waypoints, approach), so ordering is an asymmetric travelling-salesman path in two
linked parts. It is solved by nearest-neighbour construction, then best-improvement local search over the
2-opt (reverse a stretch) and Or-opt (move a stretch of 1-3 poses, either way round) neighbourhoods,
evaluated in batches with numpy, then a fixed number of seeded double-bridge kicks (iterated local search).
A move whose waypoints leave the leg limits (legs are not linear in the pose) is priced out of the route.

Constraint: a temperature drift must not look like one region of the workspace. A drift makes every leg
grow by alpha L_ik (T(t_k) - 20 °C); if the visit time t_k of the measure rows follows the workspace
(as a short route tends to), the 42 geometric parameters absorb the drift and thermal diagnosis loses it.
``drift_confounding`` measures the fraction of the drift's signature that the geometric model absorbs;
the ordered route keeps it at or below that of a typical (median) random order, the design-of-experiments
remedy for time trends.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from hilcal.error_models import constraint_jacobian
from hilcal.kinematics import N_LEGS, Geometry, inverse_kinematics, split_pose
from hilcal.planning.machine_time import MotionRules, MotionTiming, move_costs

_COLUMNS_PER_LEG = 7
_CANDIDATES_CHECKED = 64
_KICK_TRIES = 8
"""Double bridges tried per kick of the measure part; the first within the confounding bound is taken."""
UNSAFE_MOVE_S = 1e6
"""Cost of a move that leaves the leg limits: far more than any route, so it is used only if unavoidable."""


@dataclass(frozen=True)
class DriftConfounding:
    """How much a linear drift over the visit times looks like geometry (0: not at all, 1: entirely).

    absorbed_fraction: the share of the (mean-free) leg-length signature L_ik (t_k - mean t) that the
    rigid model's 7 columns per leg reproduce (least squares), over all legs. max_abs_corr_pose: the
    largest |Pearson correlation| of visit time with one pose coordinate.
    """

    absorbed_fraction: float
    max_abs_corr_pose: float


def _drift_weights(geom: Geometry, poses: np.ndarray, counts: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(W [n, 42], wL [n, 6], w [n]) for ``_absorbed``: pose k stands for counts[k] rows measured together.

    W[:, 7i:7i+7] is an orthonormal basis of sqrt(w) times leg i's geometric columns, times sqrt(w) L_i.
    """
    w = np.ones(len(poses)) if counts is None else np.asarray(counts, dtype=float)
    s = np.sqrt(w)[:, None]
    R, t = split_pose(poses)
    G = constraint_jacobian(geom, R, t)
    legs = inverse_kinematics(geom, poses)
    blocks = [np.linalg.qr(s * G[:, i, _COLUMNS_PER_LEG * i:_COLUMNS_PER_LEG * (i + 1)])[0] * (s * legs[:, i:i + 1])
              for i in range(N_LEGS)]
    return np.hstack(blocks), w[:, None] * legs, w


def _absorbed(weights: tuple[np.ndarray, np.ndarray, np.ndarray], times: np.ndarray) -> np.ndarray:
    """absorbed_fraction [C] for visit times [C, n] of the n poses (in the pose order of the weights).

    The drift signature of leg i is v_i = L_i * tau (tau the weighted mean-free times); the share explained
    by the leg's 7 columns (which include the constant dl0 column) beyond its mean, summed over the legs.
    """
    W, wL, w = weights
    tau = times - (times @ w / w.sum())[..., None]
    mean_part = np.sum((tau @ wL) ** 2, axis=-1) / w.sum()
    explained = np.sum((tau @ W) ** 2, axis=-1) - mean_part
    total = tau**2 @ np.sum(wL * wL / w[:, None], axis=1) - mean_part
    return np.where(total > 0, explained / np.where(total > 0, total, 1.0), 0.0)


def drift_confounding(geom: Geometry, poses: np.ndarray, times_s: np.ndarray, counts: np.ndarray | None = None
                      ) -> DriftConfounding:
    """Drift confounding of measure rows at `poses` [n, 6] visited at `times_s` [n] (any time unit).

    counts[k]: how many rows pose k stands for (a pose measured several times in a row).
    """
    q = np.asarray(poses, dtype=float)
    t = np.asarray(times_s, dtype=float)
    if len(q) < _COLUMNS_PER_LEG + 1:
        raise ValueError(f"need at least {_COLUMNS_PER_LEG + 1} poses, got {len(q)}")
    absorbed = float(_absorbed(_drift_weights(geom, q, counts), t[None])[0])
    spread = q.std(axis=0) > 0
    corr = [abs(float(np.corrcoef(t, q[:, j])[0, 1])) for j in np.flatnonzero(spread)] if t.std() > 0 else [0.0]
    return DriftConfounding(absorbed, max(corr, default=0.0))


@dataclass(frozen=True)
class RouteOrder:
    """The ordered route: permutations of the given measure and verify poses and what they cost.

    motion_s is the route's motion time (home, measure, verify, verify again, home; s), design_motion_s that
    of the given order. confounding is of the measure rows, bound the limit it was held to.
    """

    measure_order: np.ndarray
    verify_order: np.ndarray
    motion_s: float
    design_motion_s: float
    confounding: DriftConfounding
    design_confounding: DriftConfounding
    confounding_bound: float
    solver_s: float
    seed: int
    unsafe_moves: int = 0
    """Moves of the route whose waypoints leave the leg limits (0 unless no safe route was found)."""


@lru_cache(maxsize=32)
def _neighbourhood(k: int) -> np.ndarray:
    """Position permutations [C, k] of the 2-opt and Or-opt (1-3 poses, both ways round) moves."""
    pos = np.arange(k)
    tables = []
    i, j = np.triu_indices(k, 1)
    p = pos[None, :]
    inside = (p >= i[:, None]) & (p <= j[:, None])
    tables.append(np.where(inside, i[:, None] + j[:, None] - p, p))
    for length in (1, 2, 3):
        for start in range(k - length + 1):
            seg = pos[start:start + length]
            rest = np.delete(pos, seg)
            for at in range(len(rest) + 1):
                for piece in ((seg, seg[::-1]) if length > 1 else (seg,)):
                    tables.append(np.concatenate([rest[:at], piece, rest[at:]])[None])
    table = np.unique(np.concatenate(tables), axis=0)
    return table[np.any(table != pos, axis=1)]


def _double_bridge(seq: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    if len(seq) < 8:
        return seq[rng.permutation(len(seq))]
    a, b, c = np.sort(rng.choice(np.arange(1, len(seq)), 3, replace=False))
    return np.concatenate([seq[:a], seq[b:c], seq[a:b], seq[c:]])


CostFn = Callable[[np.ndarray], np.ndarray]
"""Candidate sequences [C, k] -> cost [C]."""
ViolationFn = Callable[[np.ndarray], np.ndarray]
"""Candidate sequences [C, k] -> how far each exceeds the confounding bound [C] (0: within it)."""


def _better(viol: float, cost: float, than_viol: float, than_cost: float) -> bool:
    """Lexicographic: less violation first, then less cost."""
    if viol < than_viol - 1e-12:
        return True
    return viol <= than_viol + 1e-12 and cost < than_cost - 1e-9


def _local_search(seq: np.ndarray, cost_fn: CostFn, viol_fn: ViolationFn | None = None
                  ) -> tuple[np.ndarray, float, float]:
    """Best-improvement descent on (violation, cost), lexicographically, over the 2-opt/Or-opt moves.

    While the sequence is within the bound only cheaper candidates are checked for violation (the cheapest
    few first, then all the others at once), so the confounding measure is computed for few candidates.
    """
    def violation(seqs: np.ndarray) -> np.ndarray:
        return np.zeros(len(seqs)) if viol_fn is None else viol_fn(seqs)

    cost, viol = float(cost_fn(seq[None])[0]), float(violation(seq[None])[0])
    table = _neighbourhood(len(seq)) if len(seq) > 1 else np.zeros((0, len(seq)), dtype=int)
    while len(table):
        cands = seq[table]
        c = cost_fn(cands)
        best = None
        if viol > 0:
            v = violation(cands)
            k = int(np.lexsort((c, np.round(v, 12)))[0])
            best = k if _better(float(v[k]), float(c[k]), viol, cost) else None
        else:
            cheaper = np.flatnonzero(c < cost - 1e-9)
            cheaper = cheaper[np.argsort(c[cheaper], kind="stable")]
            first = cheaper[:_CANDIDATES_CHECKED]
            ok = first[violation(cands[first]) <= 0] if first.size else first
            if not ok.size and len(cheaper) > len(first):
                rest = cheaper[len(first):]
                ok = rest[violation(cands[rest]) <= 0]
            if ok.size:
                best = int(ok[0])
        if best is None:
            break
        seq, cost, viol = cands[best], float(c[best]), float(violation(cands[best][None])[0])
    return seq, cost, viol


def _nearest_neighbour(D: np.ndarray, start: int, nodes: np.ndarray) -> np.ndarray:
    left = list(nodes)
    out, at = [], start
    while left:
        k = int(np.argmin(D[at, left]))
        at = left.pop(k)
        out.append(at)
    return np.array(out, dtype=int)


def order_route(geom: Geometry, home: np.ndarray, measure: np.ndarray, verify: np.ndarray, rules: MotionRules,
                timing: MotionTiming, *, measure_counts: np.ndarray | None = None, seed: int = 0, n_kicks: int = 40,
                confounding_bound: float | None = None, n_random: int = 200,
                leg_limits: tuple[float, float] | None = None) -> RouteOrder:
    """Order measure and verify poses for the least motion time, measure-row drift confounding bounded.

    measure_counts[k] is how often measure pose k is measured in a row (repeats cost time but not order).
    confounding_bound None: the median absorbed fraction of `n_random` seeded random measure orders.
    leg_limits: a move whose waypoints leave them costs UNSAFE_MOVE_S, so the route avoids it when it can
    (the plan's check refuses a route that still has one).
    """
    t0 = time.perf_counter()
    home = np.asarray(home, dtype=float)
    M, V = np.atleast_2d(measure).astype(float), np.atleast_2d(verify).astype(float).reshape(-1, 6)
    m, v = len(M), len(V)
    counts = np.ones(m, dtype=int) if measure_counts is None else np.asarray(measure_counts, dtype=int)
    nodes = np.vstack([home, M, V])
    N = len(nodes)
    ii, jj = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    moves = move_costs(geom, nodes[ii.ravel()], nodes[jj.ravel()], rules, timing)
    back = move_costs(geom, nodes, np.repeat(home[None], N, 0), rules, timing, approach=False)
    D_true, home_true = moves.time_s.reshape(N, N), back.time_s
    unsafe, unsafe_home = np.zeros((N, N), dtype=bool), np.zeros(N, dtype=bool)
    if leg_limits is not None:
        unsafe, unsafe_home = ~moves.within(leg_limits).reshape(N, N), ~back.within(leg_limits)
    D, to_home = D_true + UNSAFE_MOVE_S * unsafe, home_true + UNSAFE_MOVE_S * unsafe_home
    flat = D.ravel()
    repeat = move_costs(geom, M[:1], M[:1], rules, timing).time_s[0]
    dwell_m = timing.settle_s + timing.cmm_s_per_pose
    dwell = counts * dwell_m + (counts - 1) * repeat
    weights = _drift_weights(geom, M, counts)
    rng = np.random.default_rng(seed)

    def measure_times(seqs: np.ndarray) -> np.ndarray:
        """Arrival times [C, m] at each measure pose (in the pose order of M) along measure sequences."""
        prev = np.concatenate([np.zeros((len(seqs), 1), dtype=int), seqs[:, :-1]], axis=1)
        waits = np.concatenate([np.zeros((len(seqs), 1)), dwell[seqs[:, :-1] - 1]], axis=1)
        arrive = np.cumsum(D_true[prev, seqs] + waits, axis=1)
        out = np.empty_like(arrive)
        np.put_along_axis(out, seqs - 1, arrive, axis=1)
        return out

    if confounding_bound is None:
        perms = np.argsort(rng.random((n_random, m)), axis=1) + 1
        confounding_bound = float(np.median(_absorbed(weights, measure_times(perms))))

    def path(seqs: np.ndarray) -> np.ndarray:
        return flat.take(seqs[:, :-1] * N + seqs[:, 1:]).sum(axis=1) if seqs.shape[1] > 1 else np.zeros(len(seqs))

    def measure_violation(seqs: np.ndarray) -> np.ndarray:
        return np.maximum(0.0, _absorbed(weights, measure_times(seqs)) - confounding_bound)

    def verify_cost(seqs: np.ndarray, last_m: int) -> np.ndarray:
        return D[last_m, seqs[:, 0]] + 2 * path(seqs) + D[seqs[:, -1], seqs[:, 0]] + to_home[seqs[:, -1]]

    def total(mseq: np.ndarray, vseq: np.ndarray) -> float:
        cost = D[0, mseq[0]] + path(mseq[None])[0]
        return float(cost + (verify_cost(vseq[None], mseq[-1])[0] if v else to_home[mseq[-1]]))

    def descend(mseq: np.ndarray, vseq: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Local search on the measure part, then the verify part, again while the poses joining them change."""
        viol, search_m, search_v = 0.0, True, bool(v)
        while search_m or search_v:
            if search_m:
                first_v = int(vseq[0]) if v else -1

                def measure_cost(seqs: np.ndarray, first_v: int = first_v) -> np.ndarray:
                    end = D[seqs[:, -1], first_v] if v else to_home[seqs[:, -1]]
                    return D[0, seqs[:, 0]] + path(seqs) + end

                last_m = int(mseq[-1])
                mseq, _, viol = _local_search(mseq, measure_cost, measure_violation if m > _COLUMNS_PER_LEG else None)
                search_v = search_v or int(mseq[-1]) != last_m
                search_m = False
            if search_v:
                first_v = int(vseq[0])
                vseq, _, _ = _local_search(vseq, lambda s, last=int(mseq[-1]): verify_cost(s, last))
                search_m = int(vseq[0]) != first_v
                search_v = False
        return mseq, vseq, total(mseq, vseq), viol

    design_m, design_v = np.arange(m) + 1, np.arange(v) + 1 + m
    mseq = _nearest_neighbour(D, 0, design_m)
    vseq = _nearest_neighbour(D, int(mseq[-1]), design_v) if v else design_v
    mseq, vseq, cost, viol = descend(mseq, vseq)
    check = measure_violation if m > _COLUMNS_PER_LEG else (lambda seqs: np.zeros(len(seqs)))
    for _ in range(n_kicks):
        kicked_m, kicked_v = mseq, vseq
        if v < 8 or rng.random() < 0.5:
            tries = np.array([_double_bridge(mseq, rng) for _ in range(_KICK_TRIES)])
            within = np.flatnonzero(check(tries) <= 0)
            kicked_m = tries[within[0]] if within.size else mseq
        if kicked_m is mseq and v >= 8:
            kicked_v = _double_bridge(vseq, rng)
        cand = descend(kicked_m, kicked_v)
        if _better(cand[3], cand[2], viol, cost):
            mseq, vseq, cost, viol = cand
    if total(design_m, design_v) < cost:
        mseq, vseq, cost = design_m, design_v, total(design_m, design_v)
    repeat_s = float(((counts - 1) * repeat).sum())

    def route(mseq: np.ndarray, vseq: np.ndarray) -> tuple[np.ndarray, int]:
        """(time s, moves that leave the leg limits) of home, measure, verify, verify, home."""
        seq = np.concatenate([[0], mseq, vseq, vseq])
        return (float(D_true[seq[:-1], seq[1:]].sum() + home_true[seq[-1]]),
                int(unsafe[seq[:-1], seq[1:]].sum() + unsafe_home[seq[-1]]))

    def confounding(seq: np.ndarray) -> DriftConfounding:
        return drift_confounding(geom, M, measure_times(seq[None])[0], counts)

    motion_s, n_unsafe = route(mseq, vseq)
    return RouteOrder(
        measure_order=mseq - 1, verify_order=vseq - 1 - m, motion_s=motion_s + repeat_s,
        design_motion_s=route(design_m, design_v)[0] + repeat_s, confounding=confounding(mseq),
        design_confounding=confounding(design_m), confounding_bound=confounding_bound,
        solver_s=time.perf_counter() - t0, seed=seed, unsafe_moves=n_unsafe)
