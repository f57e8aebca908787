"""A troupe's per-row arrays (`service.rows.Rows`, `service.crowd.Troupe`): joins, leaves and
partial ticks touch the rows they name and no others (the whole troupe was copied for each),
and every character keeps its own row's values through any sequence of them."""

from __future__ import annotations

import numpy as np
import pytest

from models.registry import load_models
from models.settings import get_settings
from service.crowd import Troupe, take_rows
from service.rows import Rows


def test_rows_append_and_remove_keep_each_rows_values():
    rng = np.random.default_rng(0)
    rows = Rows()
    alive: dict[int, float] = {}
    next_id = 0
    for _ in range(200):
        k = int(rng.integers(1, 40))
        ids = np.arange(next_id, next_id + k)
        next_id += k
        rows.append({"id": ids, "value": ids * 1.5, "wide": np.repeat(ids[:, None], 3, 1)})
        alive.update({int(i): i * 1.5 for i in ids})
        if len(rows) > 5:
            gone = rng.choice(len(rows), size=int(rng.integers(1, len(rows) // 2)), replace=False)
            for i in rows.view("id")[gone]:
                del alive[int(i)]
            moved_from, moved_to = rows.remove(gone)
            assert len(moved_from) == len(moved_to) <= len(gone)
        assert sorted(rows.view("id").tolist()) == sorted(alive)
        assert np.array_equal(rows.view("value"), rows.view("id") * 1.5)
        assert np.array_equal(rows.view("wide"), np.repeat(rows.view("id")[:, None], 3, 1))
    rows.remove(np.arange(len(rows)))
    assert len(rows) == 0 and len(rows._buf["value"]) <= 16  # memory handed back once emptied


@pytest.fixture(scope="module")
def lti():
    return load_models(get_settings().weights_dir)["lti"]


def test_a_partial_tick_join_and_leave_touch_only_their_rows(lti):
    """No whole-state copy: the arrays stay where they were (a partial tick used to build new
    ones of the whole troupe), and only the named rows change."""
    troupe = Troupe(lti, 30.0)
    style = {lti.styles()[0]: 1.0}
    troupe.add(list(range(100)), [style] * 100)
    key = next(k for k, v in troupe.state.items() if v.dtype == np.float64 and v.ndim == 2)
    troupe.state[key][:] = np.arange(100)[:, None]  # each row marked with its id
    before = troupe.state[key]
    rows = troupe.rows([3, 50, 97])
    new = take_rows(troupe.state, rows)
    new[key] = new[key] + 1000.0
    troupe.put_rows(rows, new)
    after = troupe.state[key]
    assert np.shares_memory(before, after)  # written in place
    changed = np.flatnonzero(after[:, 0] >= 1000)
    assert sorted(troupe.ids[changed].tolist()) == [3, 50, 97]
    troupe.add([100, 101], [style] * 2)  # room to spare: no reallocation for a small join
    assert np.shares_memory(before, troupe.state[key])
    troupe.remove([0, 50])  # the last rows fill the holes; every id keeps its own values
    values = troupe.state[key][:, 0]
    for i, row in troupe.row_of.items():
        assert troupe.ids[row] == i
        if i < 100:
            assert values[row] == i + (1000 if i in (3, 97) else 0), i
    assert sorted(troupe.row_of) == [i for i in range(102) if i not in (0, 50)]


def test_a_large_troupe_steps_in_parts_that_give_the_whole_steps_replies(lti):
    """A troupe's step goes to the batcher `part_rows` rows at a time, one part after the other (a
    neighbour's frame is stepped before the next part rather than after the whole troupe),
    and the outputs and states are those of one whole step, to round-off: LTI's dense product
    runs over the sessions of a style a chunk at a time, and BLAS may round a chunk of 11
    differently from one of 32."""
    import asyncio

    from models.interface import FrameBatch
    from service.crowd import CrowdStep

    rng = np.random.default_rng(1)
    n = 300
    root = rng.normal(size=(n, 3)) + [0.0, 92.0, 0.0]
    rot = rng.normal(size=(n, 22, 4))
    rot /= np.linalg.norm(rot, axis=-1, keepdims=True)
    sizes: list[int] = []

    async def step_rows(state, r, q, weights, names, control):
        sizes.append(len(r))
        out, new = lti.step_batch(state, FrameBatch(r, q), weights)
        return out.root, out.rotations, new

    def run(part_rows: int):
        troupe = Troupe(lti, 30.0)
        troupe.add(list(range(n)), [{lti.styles()[i % 3]: 1.0} for i in range(n)])
        rows = troupe.rows(list(range(n)))
        for _ in range(3):
            asyncio.run(troupe.step(CrowdStep(step_rows, part_rows), rows, root, rot))
        return troupe.held_rot.copy(), {k: v.copy() for k, v in troupe.state.items()}

    whole_rot, whole_state = run(10_000)
    sizes.clear()
    parts_rot, parts_state = run(128)
    assert max(sizes) == 128 and sum(sizes) == 3 * n
    assert np.allclose(parts_rot, whole_rot, rtol=0.0, atol=1e-9)
    for key, value in whole_state.items():
        assert np.allclose(parts_state[key], value, rtol=1e-12, atol=1e-9), key
