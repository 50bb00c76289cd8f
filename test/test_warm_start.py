"""Where a chain's cells start (`kneeseat_core.sweep.chains`): the neighbour's rest carried
to the cell, plus the change of rest expected over the step - the one the ribs beside made
over the same varus step, or else the rib's own last change once more - and which ribs a rib
learns from (`kneeseat_core.sweep.phases`)."""
from __future__ import annotations

from functools import cache
import math

import numpy as np

from kneeseat_core.geometry import carried, pose_from, rotation_about
from kneeseat_core.sweep import mean_change, ribs_beside, warm_start
from kneeseat_core.sweep.chains import rest_change
from kneeseat_core.sweep.phases import FARTHEST_BESIDE
from kneeseat_core.typed import Floats, Pose

PUSH = np.array([0.0, -1.0, 0.0])
X, Y, Z = np.eye(3)


def attitude(f: int, v: int) -> Floats:
    """A commanded attitude that changes with flexion and varus."""
    return rotation_about(X, 0.02 * f) @ rotation_about(Y, 0.01 * v)


def rest(f: int, v: int) -> Pose:
    """A field of rests that bends across both axes (relative to the joint, then turned by
    the cell's attitude): its change along varus differs from rib to rib and from step to
    step, so a rib's own last change misses and the ribs' beside does not."""
    relative = pose_from(rotation_about(Z, 0.01 * f * v),
                         np.array([1e-3 * f * v, 2e-4 * v * v, 1e-4 * f]))
    return pose_from(attitude(f, v) @ relative[:3, :3], attitude(f, v) @ relative[:3, 3])


def test_a_start_from_the_ribs_beside_lands_on_a_field_of_rests_that_bends() -> None:
    f, v = 5, 3
    change = mean_change([(rest(g, v - 1), attitude(g, v - 1), rest(g, v), attitude(g, v))
                          for g in (f - 1, f + 1)], attitude(f, v))
    start = warm_start(rest(f, v - 1), attitude(f, v - 1), attitude(f, v), PUSH, 0.0,
                       change=change)
    assert np.allclose(start, rest(f, v), rtol=0.0, atol=1e-12)
    # the rib's own change once more misses the bend along varus (0.4 mm)
    own = warm_start(rest(f, v - 1), attitude(f, v - 1), attitude(f, v), PUSH, 0.0,
                     before=(rest(f, v - 2), attitude(f, v - 2)))
    assert np.linalg.norm(own[:3, 3] - rest(f, v)[:3, 3]) > 1e-4
    # either way the start is a rigid pose, backed off along the push
    backed = warm_start(rest(f, v - 1), attitude(f, v - 1), attitude(f, v), PUSH, 1e-3,
                        change=change)
    assert np.allclose(backed[:3, 3], rest(f, v)[:3, 3] - 1e-3 * PUSH, rtol=0.0, atol=1e-12)
    assert np.allclose(backed[:3, :3] @ backed[:3, :3].T, np.eye(3), rtol=0.0, atol=1e-12)


def test_the_mean_change_over_a_rib_s_steps_is_each_step_s_change_averaged_bit_for_bit(
) -> None:
    # the steps are taken at once (stacks of products); each step's change, made alone as
    # `rest_change` of the two rests `carried` to the cell, must come out the same to the
    # bit, or a table would move with how many ribs a cell learns from
    rng = np.random.default_rng(7)

    def turn() -> Floats:
        axis = rng.normal(size=3)
        return rotation_about(axis / np.linalg.norm(axis), rng.uniform(-0.5, 0.5))

    for count in range(1, 6):
        steps = [(pose_from(turn(), rng.normal(size=3) * 1e-2), turn(),
                  pose_from(turn(), rng.normal(size=3) * 1e-2), turn()) for _ in range(count)]
        cell = turn()
        alone = np.mean([rest_change(carried(older, older_turn, cell),
                                     carried(newer, newer_turn, cell))
                         for older, older_turn, newer, newer_turn in steps], axis=0)
        assert mean_change(steps, cell).tobytes() == alone.tobytes()


def test_a_rib_learns_from_the_ribs_beside_it_in_a_few_rounds() -> None:
    rounds = int(math.log2(FARTHEST_BESIDE)) + 1
    for centre, count in ((0, 91), (45, 91), (2, 7)):
        @cache
        def round_of(f: int) -> int:
            beside = ribs_beside(f, centre, count)
            return 1 + max(round_of(g) for g in beside) if beside else 0

        for f in range(count):
            k = abs(f - centre)
            step = next((s for s in (1, 2, 4, 8, 16, 32, 64) if k % (2 * s)), 0)
            beside = ribs_beside(f, centre, count)
            if k and step <= FARTHEST_BESIDE:     # the two the largest power of two away
                assert beside == [g for g in (f - step, f + step) if 0 <= g < count]
            else:                                 # the first round learns from none
                assert beside == []
        # however long the grid, a rib waits for a few rounds of ribs at most
        most = max(round_of(f) for f in range(count))
        assert most == rounds if count > 2 * FARTHEST_BESIDE else most <= rounds
