"""OMPL search on an analytic cost map: every planner detours around a high-variance disk
with the hard tube, seeded runs repeat, simplification never raises the cost, and the
caller's threads keep running while a worker plans."""

import itertools
import threading
import time

import numpy as np
import pytest

from planner.costmap import CostMap, CostWeights
from planner.dijkstra import lattice_optimum
from planner.search import PLANNERS, Box, PlanningProblem, solve_in_workers

pytestmark = pytest.mark.slow  # OMPL planners run for seconds

AXES = (np.linspace(0, 2000, 41), np.linspace(0, 2000, 41), np.linspace(0, 300, 7))
START, GOAL = (100.0, 1000.0, 100.0), (1900.0, 1000.0, 100.0)


def densify(P: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points along the polyline every ``spacing_m`` at most, vertices included."""
    parts = []
    for a, b in itertools.pairwise(P):
        n = max(int(np.ceil(np.linalg.norm(b - a) / spacing_m)), 1)
        parts.append(a + np.linspace(0, 1, n, endpoint=False)[:, None] * (b - a))
    return np.vstack([*parts, P[-1:]])


@pytest.fixture(scope="module")
def blocked() -> CostMap:
    """Low std everywhere but a disk of radius 600 m on the straight line; flow to the east."""
    G = np.stack(np.meshgrid(*AXES, indexing="ij"), -1)
    s = np.where(np.hypot(G[..., 0] - 1000, G[..., 1] - 1000) < 600, 5.0, 0.5)
    mean = np.zeros((*s.shape, 3))
    mean[..., 0] = 10.0
    return CostMap(AXES, mean, np.repeat(s[..., None], 3, -1), CostWeights(max_std_mps=1.0))


@pytest.mark.parametrize("planner", PLANNERS)
def test_every_planner_detours_inside_the_tube(blocked, planner):
    # bounded by seeded iterations, not the clock (BIT* needs more, its iterations are cheap)
    iterations = 1000 if planner == "bitstar" else 300
    problem = PlanningProblem(
        blocked, START, GOAL, planner=planner, time_s=120.0, max_iterations=iterations, fmt_samples=60, seed=1
    )
    assert not problem.segments_valid(np.array([START]), np.array([GOAL]))[0]
    sol = solve_in_workers([problem])[0]
    assert sol.exact, sol.status
    P = sol.waypoints
    np.testing.assert_allclose(P[0], START)
    np.testing.assert_allclose(P[-1], GOAL, atol=1e-3)
    assert problem.segments_valid(P[:-1], P[1:]).all()
    assert (blocked.max_std(densify(P, 5.0)) <= 1.0).all()
    assert sol.cost == pytest.approx(problem.path_cost(P), rel=1e-12)
    # around the disk: longer than the straight 1,800 m, shorter than going around it twice
    assert 1800 < np.linalg.norm(np.diff(P, axis=0), axis=1).sum() < 3600
    assert sol.calls["motion_cost"] > 0 and sol.callback_s > 0


def test_seeded_iteration_bounded_runs_repeat_and_simplifying_never_raises_the_cost(blocked):
    runs = solve_in_workers(
        [
            PlanningProblem(
                blocked, START, GOAL, planner="rrtstar", seed=seed, max_iterations=400, simplify=simplify
            )
            for seed, simplify in ((7, True), (7, True), (8, True), (7, False))
        ]
    )
    np.testing.assert_array_equal(runs[0].waypoints, runs[1].waypoints)
    assert not np.array_equal(runs[0].waypoints, runs[2].waypoints)
    assert runs[0].cost <= runs[3].cost  # the same run, simplified and not


def test_no_fly_box_is_avoided_by_the_shortest_path(blocked):
    wall = Box((900.0, 0.0, 0.0), (1100.0, 1500.0, 300.0))
    problem = PlanningProblem(blocked, START, GOAL, no_fly=(wall,), objective="length", time_s=1.5)
    sol = solve_in_workers([problem])[0]
    assert sol.exact and not wall.hits(sol.waypoints[:-1], sol.waypoints[1:]).any()
    assert sol.waypoints[:, 1].max() > 1500  # over the wall's end: the only way round


def test_planning_in_a_worker_leaves_the_callers_threads_running(blocked):
    ticks, done = [0], threading.Event()

    def tick():
        while not done.is_set():
            ticks[0] += 1
            time.sleep(0.01)

    thread = threading.Thread(target=tick)
    thread.start()
    t0 = time.perf_counter()
    solve_in_workers([PlanningProblem(blocked, START, GOAL, time_s=1.5)])[0]
    elapsed = time.perf_counter() - t0
    done.set()
    thread.join()
    assert ticks[0] > 0.5 * elapsed / 0.01  # a solve in this process would hold the GIL throughout


def test_lattice_optimum_bounds_the_planner_from_near_and_matches_a_straight_corridor(blocked):
    problem = PlanningProblem(blocked, START, GOAL, time_s=2.0, seed=3)
    lattice_cost, P = lattice_optimum(problem)
    assert problem.segments_valid(P[1:-2], P[2:-1]).all()
    sol = solve_in_workers([problem])[0]
    # the sampling planner is near the lattice optimum (which is only 26-connected)
    assert 0.8 * lattice_cost < sol.cost < 1.3 * lattice_cost
    # along an axis-aligned, obstacle-free line, the lattice path is the straight line
    free = PlanningProblem(blocked, (100.0, 200.0, 100.0), (1900.0, 200.0, 100.0), objective="length")
    cost, _ = lattice_optimum(free)
    assert cost == pytest.approx(1800.0)
