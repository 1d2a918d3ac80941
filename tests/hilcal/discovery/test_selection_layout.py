"""The selection's candidate block: its group sums are numpy's reduceat bit for bit, and the tests of `assess` do not
depend on how the groups are laid out (width classes, the groups' order, per group or as one block) beyond
floating-point noise (a product's rounding may depend on where a column sits)."""

from __future__ import annotations

import numpy as np
import pytest

from hilcal.discovery.selection import Columns, ModelState, assess, squared_group_sums
from hilcal.discovery.term_groups import GENERIC, LIBRARY, TermGroup


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_group_sums_are_reduceat_bit_for_bit(dtype: type) -> None:
    rng = np.random.default_rng(3)
    ranks = rng.integers(1, 21, size=300)
    values = (rng.standard_normal((int(ranks.sum()), 97)) * rng.uniform(0.01, 100.0, (int(ranks.sum()), 1)))
    values = values.astype(dtype)
    starts = np.concatenate([[0], np.cumsum(ranks)[:-1]])
    expected = np.add.reduceat(values**2, starts, axis=0)
    got = squared_group_sums(values.copy(), ranks)
    assert got.dtype == dtype and np.array_equal(got, expected)


def _problem(rng: np.random.Generator, n_poses: int = 40) -> tuple[ModelState, list[TermGroup], list[np.ndarray]]:
    """A model with a signal in two of 30 groups of widths 1 to 4 (library and generic), one group the model holds."""
    J = rng.normal(size=(6 * n_poses, 12))
    widths = rng.integers(1, 5, size=30)
    columns = [rng.normal(size=(6 * n_poses, int(w))) for w in widths]
    columns[7] = J[:, :2] @ rng.normal(size=(2, int(widths[7])))  # nothing beyond the model: left out
    r = rng.normal(size=6 * n_poses) + 4.0 * columns[3][:, 0] + 3.0 * columns[11][:, -1]
    state = ModelState.build(r, J, np.eye(6), n_poses, np.arange(n_poses))
    groups = [TermGroup(f"g{j}", LIBRARY if j % 3 == 0 else GENERIC, "unexplained", f"g{j}",
                        tuple(f"p{j}_{i}" for i in range(int(w))), lambda c: None) for j, w in enumerate(widths)]
    return state, groups, columns


def _same(a: list, b: list) -> bool:
    """The same groups, ranks and p-values, and the same figures to 1e-12."""
    return all(x.group.key == y.group.key and x.rank == y.rank and (x.p_wild, x.p_gauss) == (y.p_wild, y.p_gauss)
               and np.allclose([x.f_statistic, x.press_gain_mm, *x.estimate], [y.f_statistic, y.press_gain_mm,
                                                                                 *y.estimate], rtol=1e-12, atol=0)
               for x, y in zip(a, b, strict=True))


def test_assess_does_not_depend_on_the_layout_of_the_groups() -> None:
    rng = np.random.default_rng(5)
    state, groups, columns = _problem(rng)
    tests = assess(state, groups, columns, 0.05, 199, 11)
    assert [t.group.key for t in tests] == [g.key for g in groups if g.key != "g7"]
    assert {t.group.key for t in tests if t.significant} == {"g3", "g11"}
    assert _same(assess(state, groups, Columns.of(columns), 0.05, 199, 11), tests)
    order = rng.permutation(len(groups))
    shuffled = assess(state, [groups[k] for k in order], [columns[k] for k in order], 0.05, 199, 11)
    by_key = {t.group.key: t for t in shuffled}
    assert _same([by_key[t.group.key] for t in tests], tests)
    assert not _same([by_key[t.group.key] for t in tests][::-1], tests)
