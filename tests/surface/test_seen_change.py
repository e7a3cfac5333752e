"""The damage compares two surveys where both saw the surface: a cell one of them saw only in part takes the change
of the cells around it that both saw wholly (`seen_change.py`)."""

import math

import numpy as np
import pytest

from jaxstereo import DEM
from jaxstereo._surface.coverage import partial_coverage_sigma
from jaxstereo._surface.damage_report import stretch_damage
from jaxstereo._surface.seen_change import change_where_seen

COT = 2.0
DN50 = 0.036
SPACING = 0.005
WHOLLY_SEEN = 30.0  # points in a cell seen wholly


def _rubble(cot=COT):
    """A 1:cot slope through (0, 0) (x cross-shore, y along; 5 mm cells) carrying rows of square rocks 30 mm
    across and 40 mm tall, 20 mm crevices between them. **Returns** x (nx,), y (ny,), the true heights (ny, nx)
    and the crevices' 15 mm beside each rock's downslope face (ny, nx) bool."""
    x = np.arange(-0.4, 0.6 + 1e-9, SPACING)
    y = np.arange(-0.25, 0.25 + 1e-9, SPACING)
    X, Y = np.meshgrid(x, y)
    phase_x, phase_y = np.mod(X + 0.5, 0.05), np.mod(Y + 0.5, 0.05)
    rock = (phase_x < 0.03) & (phase_y < 0.03)
    z = X / cot + 0.04 * rock
    beside = ~rock & (phase_y < 0.03) & (np.roll(rock, -1, axis=1) | np.roll(rock, -2, axis=1)
                                          | np.roll(rock, -3, axis=1))
    return x, y, z, beside


def _survey(x, y, z, hidden, reads):
    """A gridded survey: the cells in `hidden` seen in part (2 points of the 30 the cells around hold) and read at
    `reads` there; every other cell seen wholly and read true. Its coverage std from the points' counts, as
    `grid_survey` gives it."""
    read = np.where(hidden, reads, z)
    count = np.where(hidden, 2.0, WHOLLY_SEEN)
    return DEM(x, y, read, SPACING, sigma_coverage=partial_coverage_sigma(read, count))


def _damage(before, after, **kwargs):
    return stretch_damage(before, after, DN50, COT, 0.0, (0.0, 0.0), profile_spacing_m=SPACING, **kwargs)


def test_an_unmoved_model_seen_from_two_viewpoints_reads_no_damage():
    # The crevice floor beside each rock's downslope face: one survey sees the rock's top there (the window
    # straddles the edge, the floor is hidden), the other the floor. Nothing moved.
    x, y, z, beside = _rubble()
    before = _survey(x, y, z, beside, z + 0.04)
    after = _survey(x, y, z, beside, z)
    as_surveyed = _damage(before, after, seen_tolerance_m=math.inf)
    # the hidden floor reads as erosion on every row through the rocks (S 0.33 averaged, 0.44 at most)
    assert as_surveyed.S_max > 0.4 and as_surveyed.averaged.S > 0.3 and as_surveyed.carried == 0.0
    compared = _damage(before, after)
    assert compared.S_max < 1e-9 and compared.averaged.S < 1e-9
    assert compared.volumes.eroded_m3 < 1e-12
    compared_rows = (y >= compared.stretch[0]) & (y <= compared.stretch[1])
    assert compared.carried == pytest.approx(beside[compared_rows].mean(), rel=1e-9)


def test_a_hole_keeps_its_depth_where_the_after_survey_saw_its_floor_only_in_part():
    # A rock removed (a hole 35 mm deep and 60 mm across, in the middle of the slope); the after-survey saw a few
    # cells of its floor only in part and read them at the rim, as a straddling window would.
    x, y, z, _ = _rubble()
    X, Y = np.meshgrid(x, y)
    hole = (np.abs(X) < 0.03) & (np.abs(Y) < 0.03)
    z_after = z - 0.035 * hole
    i, j = np.meshgrid(np.arange(y.size), np.arange(x.size), indexing="ij")
    specks = (np.abs(X) <= 0.01) & (np.abs(Y) <= 0.01) & ((i + j) % 2 == 0)  # 13 cells, each between seen ones
    clean = _damage(DEM(x, y, z, SPACING), DEM(x, y, z_after, SPACING))
    before = _survey(x, y, z, np.zeros(z.shape, bool), z)
    after = _survey(x, y, z_after, specks, z)
    compared = _damage(before, after)
    as_surveyed = _damage(before, after, seen_tolerance_m=math.inf)
    central = dict(compared.profiles)[min(dict(compared.profiles), key=abs)]
    clean_central = dict(clean.profiles)[min(dict(clean.profiles), key=abs)]
    assert central.A_e == pytest.approx(clean_central.A_e, rel=1e-9)  # each speck takes the hole's depth
    assert compared.volumes.eroded_m3 == pytest.approx(clean.volumes.eroded_m3, rel=1e-9)
    assert as_surveyed.volumes.eroded_m3 < 0.95 * clean.volumes.eroded_m3


def test_a_pit_cell_among_rim_cells_keeps_its_depth_and_stays_within_its_neighbours_range():
    # A pit three cells long and one wide, 5 cm deep; the after-survey saw its middle cell only in part. Of that
    # cell's 8 neighbours 2 lie on the pit's floor and 6 on its rim: most agree, their MAD is nil, and the rule
    # before round 66 (the neighbours beyond 3 MADs of their median left out) left the floor cells out and read the
    # cell at the rim's change, a third of the pit gone. The whole range keeps its depth; a reading past the range
    # (a straddling window's) takes the range's nearer end.
    x = np.arange(0.0, 0.1, SPACING)
    flat = np.zeros((x.size, x.size))
    pit = np.zeros(flat.shape, bool)
    pit[10, 9:12] = True
    cell = (10, 10)
    hidden = np.zeros(flat.shape, bool)
    hidden[cell] = True
    before = DEM(x, x, flat, SPACING)
    for reads, expected in ((-0.05, -0.05), (-0.08, -0.05), (0.03, 0.0), (-0.02, -0.02)):
        after = _survey(x, x, flat - 0.05 * pit, hidden, reads)
        compared, carried = change_where_seen(before, after, 0.0, DN50)
        assert carried.sum() == 1 and carried[cell]
        assert compared.z[cell] == pytest.approx(expected)
        assert np.array_equal(compared.z[~hidden], after.z[~hidden])  # the cells seen wholly: as surveyed
    # The pit's central profile along x then holds its whole depth
    after = _survey(x, x, flat - 0.05 * pit, hidden, -0.05)
    assert np.array_equal(change_where_seen(before, after, 0.0, DN50)[0].z[10, 9:12], [-0.05] * 3)


def test_a_narrow_hole_seen_in_part_keeps_its_depth_where_its_neighbours_span_it():
    # A trench two cells wide and 4 cm deep along x; the after-survey saw its far row wholly and its near row only in
    # part (the wall hides some of it), read at the trench's depth. Each near-row cell has 3 seen neighbours on the
    # rim (no change) and 3 on the trench's floor (-4 cm): its own change lies in their range and is kept; their
    # median, -2 cm, would have made the trench half as deep there.
    x = np.arange(0.0, 0.1, SPACING)
    flat = np.zeros((x.size, x.size))
    trench = np.zeros(flat.shape, bool)
    trench[9:11, :] = True
    near = np.zeros(flat.shape, bool)
    near[9, :] = True
    before = DEM(x, x, flat, SPACING)
    after = _survey(x, x, flat - 0.04 * trench, near, flat - 0.04)
    compared, carried = change_where_seen(before, after, 0.0, DN50)
    assert np.array_equal(carried, near)
    np.testing.assert_allclose(compared.z[9, 1:-1], -0.04)
    # A reading beyond the neighbours' range takes its nearer end: a near-row cell read 3 cm below the floor
    deeper = _survey(x, x, flat - 0.04 * trench, near, np.where(near, -0.07, flat))
    np.testing.assert_allclose(change_where_seen(before, deeper, 0.0, DN50)[0].z[9, 1:-1], -0.04)


def test_a_hole_floor_corner_seen_in_part_keeps_its_depth_from_floor_cells_within_the_foot():
    # A hole 5 cm deep, its floor 4 x 4 cells; the after-survey saw a corner of it, 2 x 2 cells, only in part (the
    # walls hide some of each), read at the floor's depth. The corner cell's wholly seen 3 x 3 neighbours all lie
    # on the rim (no change), so with them alone it took the rim's change, a step 5 cm high inside the hole that the
    # profiler's foot cannot pass (flume V, round 68); the floor cells seen wholly two cells away, within a quarter of
    # a stone, span the hole's depth and keep it.
    x = np.arange(0.0, 0.12, SPACING)
    flat = np.zeros((x.size, x.size))
    hole = np.zeros(flat.shape, bool)
    hole[10:14, 10:14] = True
    corner = np.zeros(flat.shape, bool)
    corner[10:12, 10:12] = True
    before = DEM(x, x, flat, SPACING)

    def surveyed(reads):  # the corner's coverage std as a DEM file gives it (its own cells' relief is nil here)
        return DEM(x, x, np.where(corner, reads, flat - 0.05 * hole), SPACING, sigma_coverage=0.01 * corner)

    assert round(0.25 * DN50 / SPACING) == 2  # the cells looked at: 5 x 5 around each
    compared, carried = change_where_seen(before, surveyed(-0.05), 0.0, DN50)
    assert np.array_equal(carried, corner)
    np.testing.assert_allclose(compared.z[corner], -0.05)
    # read past the floor (a straddling window's), each takes the range's nearer end: the floor again
    np.testing.assert_allclose(change_where_seen(before, surveyed(-0.08), 0.0, DN50)[0].z[corner], -0.05)
    # read at the rim, each keeps its own reading (within the range): nothing invents a depth the survey did not see
    np.testing.assert_allclose(change_where_seen(before, surveyed(0.0), 0.0, DN50)[0].z[corner], 0.0)


def test_a_cell_with_no_seen_neighbour_takes_the_nearest_within_a_stone_and_no_farther():
    x = np.arange(0.0, 0.2, SPACING)
    flat = np.zeros((x.size, x.size))
    hidden = np.zeros(flat.shape, bool)
    hidden[:, 21:] = True  # the before-survey saw the right part only in part (as a DEM file would say)
    before = DEM(x, x, flat + 0.02 * hidden, SPACING, sigma_coverage=0.01 * hidden)
    sunk = flat.copy()
    sunk[:, :21] = -0.01  # the left part sank 1 cm by the after-survey, which saw it all
    after = DEM(x, x, sunk, SPACING)  # no coverage layer: seen wholly wherever it has a height
    compared, carried = change_where_seen(before, after, 0.0, DN50)
    reach = int(DN50 / SPACING)  # 7 cells
    assert carried[:, 21 : 21 + reach].all() and not carried[:, 21 + reach :].any()
    # beside column 20 the median of its three cells' changes, farther the nearest one's: -1 cm each
    assert np.allclose(compared.z[:, 21 : 21 + reach], before.z[:, 21 : 21 + reach] - 0.01)
    assert np.array_equal(compared.z[:, 21 + reach :], after.z[:, 21 + reach :])
    # Without coverage layers nothing is carried (a DEM of the true surfaces, say)
    plain, none = change_where_seen(DEM(x, x, before.z, SPACING), after, 0.0, DN50)
    assert not none.any() and plain is after
    # Nothing seen wholly by both: nothing to take a change from
    unseen_all = DEM(x, x, flat, SPACING, sigma_coverage=np.full(flat.shape, 0.01))
    same, none = change_where_seen(unseen_all, after, 0.0, DN50)
    assert not none.any() and same is after
