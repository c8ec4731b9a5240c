"""The demo's choice of route: across the busiest flow, between tube points on its two sides."""

import numpy as np
import pytest

from bdf.ingest import Observations
from clients.demo import across_flow, busiest_flow

pytestmark = pytest.mark.slow  # the demo end to end


def test_the_busiest_flow_is_the_cell_most_flights_cross_and_their_heading():
    rng = np.random.default_rng(0)
    rows = []
    for f in range(30):  # a westbound corridor along y = 5 km at 1,500 m, 1 Hz at 200 m/s
        x = np.arange(20_000, -20_000, -200.0)
        rows.append((np.column_stack([x, 5000 + rng.normal(0, 50, len(x)), np.full(len(x), 1500.0)]), f))
    for f in range(30, 40):  # ten northbound flights elsewhere, and traffic above the band
        y = np.arange(-20_000, 0, 200.0)
        rows.append((np.column_stack([np.full(len(y), -12_000.0), y, np.full(len(y), 2000.0)]), f))
    x = np.arange(-20_000, 20_000, 200.0)
    rows.append((np.column_stack([x, np.full(len(x), 5000.0), np.full(len(x), 9000.0)]), 99))
    X = np.vstack([r for r, _ in rows])
    flight = np.concatenate([np.full(len(r), f) for r, f in rows])
    V = np.where((flight < 30)[:, None], [-200.0, 0, 0], [0, 200.0, 0])
    V[flight == 99] = [200.0, 0, 0]
    obs = Observations(X, V, np.zeros(len(X)), flight)
    centre, direction, flights = busiest_flow(obs, (1000.0, 2500.0))
    assert flights == 30 and abs(centre[1] - 5000) <= 1000
    np.testing.assert_allclose(direction, [-1.0, 0.0], atol=1e-3)

    # tube points on a lattice: start on the flow's right (north of a westbound flow), goal
    # on its left, each the point nearest 15 km from the flow line through the centre
    g = np.arange(-30_000, 30_001, 1000.0)
    P = np.stack(np.meshgrid(g, g, [1500.0], indexing="ij"), -1).reshape(-1, 3)
    start, goal = across_flow(P, centre, direction, offset_m=15_000)
    np.testing.assert_allclose(start[:2], [centre[0], centre[1] + 15_000], atol=500)
    np.testing.assert_allclose(goal[:2], [centre[0], centre[1] - 15_000], atol=500)
    with pytest.raises(ValueError, match="one side of the flow"):
        across_flow(P[P[:, 1] > centre[1]], centre, direction)
