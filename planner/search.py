"""OMPL search on a :class:`~planner.costmap.CostMap` (``ompl==2.0.1``, nanobind bindings).

What the 2.0.1 bindings allow is recorded in ``docs/ompl.md``: the objective is a Python
subclass of ``PathLengthOptimizationObjective`` with ``motionCost`` (our integral) and a
straight-line ``motionCostHeuristic`` (admissible because cost >= length), validity is a
Python ``StateValidityChecker`` and ``MotionValidator``, and only ``partialShortcutPath``
simplifies without ignoring the objective. ``solve()`` holds the GIL and a seed works once
per process, so :func:`solve_in_workers` runs each problem in a fresh process (forked from a fork server).
"""

from __future__ import annotations

import math
import multiprocessing
import time
from dataclasses import dataclass, field

import numpy as np

from planner.costmap import CostMap

#: Planners by name; each takes the objective from the problem definition.
PLANNERS = ("bitstar", "rrtstar", "informed_rrtstar", "sorrtstar", "fmt")
#: What a run keeps of its deadline for simplifying its path and sending it back (s).
RETURN_S = 0.3
#: Refused with the reason measured on ompl 2.0.1 (docs/ompl.md).
UNSUPPORTED = {
    "prmstar": "PRM* deadlocks with a Python objective in ompl 2.0.1",
    "aorrtc": "AORRTC ignores the objective and crashes in metre-scale spaces in ompl 2.0.1",
}


@dataclass(frozen=True)
class Box:
    """An axis-aligned no-fly box, ENU metres."""

    lower: tuple[float, float, float]
    upper: tuple[float, float, float]

    def __post_init__(self):
        lo, hi = np.asarray(self.lower, float), np.asarray(self.upper, float)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise ValueError(f"a box needs 3 finite lower and 3 upper coordinates, got {self}")
        if np.any(hi <= lo):
            raise ValueError(f"box upper {hi.tolist()} must be above lower {lo.tolist()} on every axis")

    def contains(self, X) -> np.ndarray:
        X = np.atleast_2d(X)
        return np.all((X >= self.lower) & (X <= self.upper), axis=1)

    def hits(self, P0, P1) -> np.ndarray:
        """True per segment that touches the box (exact slab test)."""
        P0, P1 = np.atleast_2d(P0), np.atleast_2d(P1)
        d = P1 - P0
        with np.errstate(divide="ignore", invalid="ignore"):
            t0 = (np.asarray(self.lower) - P0) / d
            t1 = (np.asarray(self.upper) - P0) / d
        parallel = d == 0
        inside_slab = (P0 >= self.lower) & (P0 <= self.upper)
        lo = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t0, t1))
        hi = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t0, t1))
        enter, leave = np.max(lo, axis=1), np.min(hi, axis=1)
        return (enter <= leave) & (leave >= 0) & (enter <= 1)


@dataclass(frozen=True)
class PlanningProblem:
    """A planning problem in the cost map's ENU frame.

    ``altitude_m``: the band (min, max) to fly in (default: the grid's). ``time_s``: the
    budget; ``deadline`` (``time.time()``): when the result must be back, the search
    stopping :data:`RETURN_S` before it if that is sooner; ``max_iterations`` instead bounds
    the run by iterations, which with ``seed`` makes it reproducible. ``objective="length"``
    plans the shortest path (the baseline): no risk, no flow and no tube, only the no-fly
    boxes and the altitude band.
    """

    costmap: CostMap
    start: tuple[float, float, float]
    goal: tuple[float, float, float]
    altitude_m: tuple[float, float] | None = None
    no_fly: tuple[Box, ...] = ()
    planner: str = "bitstar"
    time_s: float = 5.0
    deadline: float | None = None
    max_iterations: int | None = None
    seed: int | None = None
    objective: str = "risk"
    simplify: bool = True
    checkpoints_s: tuple[float, ...] = ()
    fmt_samples: int = 150

    def __post_init__(self):
        if self.planner in UNSUPPORTED:
            raise ValueError(f"planner {self.planner!r} is not offered: {UNSUPPORTED[self.planner]}")
        if self.planner not in PLANNERS:
            raise ValueError(f"unknown planner {self.planner!r}; choose one of {', '.join(PLANNERS)}")
        if self.objective not in ("risk", "length"):
            raise ValueError(f"objective must be 'risk' or 'length', got {self.objective!r}")
        if not self.time_s > 0:
            raise ValueError(f"time_s must be positive, got {self.time_s}")
        if self.seed is not None and self.seed < 1:
            raise ValueError(f"seed must be a positive integer (OMPL does not take 0), got {self.seed}")
        if self.max_iterations is not None and self.max_iterations < 1:
            raise ValueError(f"max_iterations must be positive, got {self.max_iterations}")
        lower, upper = self.bounds()
        if not lower[2] < upper[2]:
            raise ValueError(
                f"the altitude band {self.altitude_m} does not overlap the grid's "
                f"{self.costmap.lower[2]} .. {self.costmap.upper[2]} m"
            )
        for name in ("start", "goal"):
            p = np.asarray(getattr(self, name), float)
            if p.shape != (3,) or not np.isfinite(p).all():
                raise ValueError(f"{name} must be 3 finite ENU coordinates, got {getattr(self, name)}")
            if np.any(p < lower) or np.any(p > upper):
                raise ValueError(
                    f"{name} {p.round(1).tolist()} is outside the planning box "
                    f"{lower.round(1).tolist()} .. {upper.round(1).tolist()} (grid and altitude band)"
                )
            if any(box.contains(p)[0] for box in self.no_fly):
                raise ValueError(f"{name} {p.round(1).tolist()} is inside a no-fly box")
            if self.hard_tube:
                s = float(self.costmap.max_std_high(p)[0])
                bound = self.costmap.weights.max_std_mps
                if s > bound:
                    raise ValueError(
                        f"{name} {p.round(1).tolist()} is outside the tube: std {s:.3g} m/s > "
                        f"max_std_mps {bound:g}; move it into the tube or use tube='soft'"
                    )

    @property
    def hard_tube(self) -> bool:
        return self.objective == "risk" and self.costmap.weights.tube == "hard"

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lower, upper = self.costmap.lower.copy(), self.costmap.upper.copy()
        if self.altitude_m is not None:
            lower[2], upper[2] = max(lower[2], self.altitude_m[0]), min(upper[2], self.altitude_m[1])
        return lower, upper

    def segments_valid(self, P0, P1) -> np.ndarray:
        """True per segment that avoids every no-fly box and (hard tube) stays in the tube."""
        ok = np.ones(len(np.atleast_2d(P0)), bool)
        for box in self.no_fly:
            ok &= ~box.hits(P0, P1)
        if self.hard_tube:
            ok &= self.costmap.segments_in_tube(P0, P1)
        return ok

    def path_cost(self, P) -> float:
        P = np.asarray(P, float)
        if self.objective == "length":
            return float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())
        return float(self.costmap.segment_costs(P[:-1], P[1:]).sum())


@dataclass
class PlanResult:
    """What a run found; picklable (it crosses the worker process boundary)."""

    waypoints: np.ndarray  # (k, 3) ENU; empty when nothing was found
    status: str
    exact: bool
    cost: float
    solve_s: float
    first_solution_s: float | None
    cost_at_s: dict[float, float | None]
    iterations: int | None
    calls: dict[str, int] = field(default_factory=dict)
    callback_s: float = 0.0


def _ompl():
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    ou.setLogLevel(ou.LOG_WARN)
    return ob, og, ou


def solve(problem: PlanningProblem) -> PlanResult:
    """Plan in this process (it blocks: ``solve()`` holds the GIL). See :func:`solve_in_workers`."""
    ob, og, ou = _ompl()
    if problem.seed is not None:
        ou.RNG.setSeed(problem.seed)
        if ou.RNG.getSeed() != problem.seed:
            raise RuntimeError(
                "OMPL's random numbers already started in this process: a seeded run "
                "needs a fresh process (solve_in_workers)"
            )
    costmap, calls, clock = problem.costmap, {"motion_cost": 0, "motion_check": 0, "state_check": 0}, [0.0]
    lower, upper = problem.bounds()

    space = ob.RealVectorStateSpace(3)
    bounds = ob.RealVectorBounds(3)
    for d in range(3):
        bounds.setLow(d, float(lower[d]))
        bounds.setHigh(d, float(upper[d]))
    space.setBounds(bounds)
    ss = og.SimpleSetup(space)
    si = ss.getSpaceInformation()

    def xyz(s):
        return (s[0], s[1], s[2])

    def timed(name: str, fn):
        """``fn`` on the states as (1, 3) arrays, counted and timed: callbacks are the cost."""

        def call(*states):
            t = time.perf_counter()
            calls[name] += 1
            out = fn(*(np.array([xyz(state)]) for state in states))
            clock[0] += time.perf_counter() - t
            return out

        return call

    last = [None, None]  # the last segment asked and its (cost, in tube): a check, then its cost

    def segment(a, b):
        key = (*a[0], *b[0])
        if last[0] != key:
            last[:] = key, costmap.segment(a[0], b[0])
        return last[1]

    def motion_valid(a, b):
        ok = all(not box.hits(a, b)[0] for box in problem.no_fly)
        return ok and (not problem.hard_tube or segment(a, b)[1])

    state_valid = timed("state_check", lambda p: bool(problem.segments_valid(p, p)[0]))
    motion_valid = timed("motion_check", motion_valid)
    motion_cost = timed("motion_cost", lambda a, b: ob.Cost(segment(a, b)[0]))

    class Checker(ob.StateValidityChecker):
        def isValid(self, s):
            return state_valid(s)

    class Motions(ob.MotionValidator):
        def checkMotion(self, s1, s2):
            return motion_valid(s1, s2)

    class Objective(ob.PathLengthOptimizationObjective):
        def motionCost(self, s1, s2):
            return motion_cost(s1, s2)

        def motionCostHeuristic(self, s1, s2):  # the C++ default would call motionCost
            return ob.Cost(math.dist(xyz(s1), xyz(s2)))

    checker, motions = Checker(si), Motions(si)
    ss.setStateValidityChecker(checker)
    si.setMotionValidator(motions)
    objective = Objective(si) if problem.objective == "risk" else ob.PathLengthOptimizationObjective(si)
    ss.setOptimizationObjective(objective)
    start, goal = space.allocState(), space.allocState()
    start[0:3] = [float(v) for v in problem.start]
    goal[0:3] = [float(v) for v in problem.goal]
    ss.setStartAndGoalStates(start, goal, 1e-6 * float(np.linalg.norm(upper - lower)))
    si.setStateValidityCheckingResolution(min(0.5, costmap.sample_m / space.getMaximumExtent()))
    planner = _planner(og, si, problem)
    ss.setPlanner(planner)

    def best() -> np.ndarray | None:
        if not ss.haveExactSolutionPath():
            return None
        path = og.PathGeometric(ss.getSolutionPath())
        return np.array([xyz(s) for s in path.getStates()])

    t0 = time.perf_counter()
    budget = problem.time_s
    if problem.deadline is not None:  # at least a few slices, to have a path at all
        budget = min(budget, max(problem.deadline - RETURN_S - time.time(), 0.2))
    first, cost_at = None, {}
    checkpoints = sorted(c for c in problem.checkpoints_s if c <= budget)
    if problem.max_iterations is not None:
        count = [0]

        def stop():
            count[0] += 1
            return count[0] > problem.max_iterations

        status = ss.solve(ob.PlannerTerminationCondition(stop))
    elif problem.planner == "fmt":  # one-shot: it does not continue a previous run
        status = ss.solve(budget)
    else:  # slices, to see when the first solution came and the cost at the checkpoints
        while (elapsed := time.perf_counter() - t0) < budget:
            horizon = next((c for c in checkpoints if c > elapsed), budget)
            status = ss.solve(min(0.05 if first is None else 0.25, horizon - elapsed, budget - elapsed))
            now = time.perf_counter() - t0
            if first is None and ss.haveExactSolutionPath():
                first = now
            for c in checkpoints:
                if c not in cost_at and now >= c - 1e-3:
                    P = best()
                    cost_at[c] = None if P is None else problem.path_cost(P)
    solve_s = time.perf_counter() - t0
    solve_calls, solve_callback_s = dict(calls), clock[0]  # simplification's calls not counted
    P = best()
    if first is None and P is not None:
        first = solve_s
    if P is not None and problem.simplify:
        P = _shortcut(og, si, ss, objective, problem, P, xyz)
    iterations = planner.numIterations() if hasattr(planner, "numIterations") else None
    return PlanResult(
        waypoints=np.empty((0, 3)) if P is None else P,
        status=status.asString(),
        exact=P is not None,
        cost=math.inf if P is None else problem.path_cost(P),
        solve_s=solve_s,
        first_solution_s=first,
        cost_at_s={c: cost_at.get(c) for c in checkpoints},
        iterations=iterations,
        calls=solve_calls,
        callback_s=solve_callback_s,
    )


def _planner(og, si, problem: PlanningProblem):
    if problem.planner == "bitstar":
        return og.BITstar(si)
    if problem.planner == "fmt":
        p = og.FMT(si)
        p.setNumSamples(problem.fmt_samples)
        return p
    cls = {"rrtstar": og.RRTstar, "informed_rrtstar": og.InformedRRTstar, "sorrtstar": og.SORRTstar}
    p = cls[problem.planner](si)
    # fewer rewiring neighbours: ~6x more iterations per second with a Python objective
    p.setRewireFactor(0.1)
    return p


def _shortcut(og, si, ss, objective, problem: PlanningProblem, P: np.ndarray, xyz) -> np.ndarray:
    """partialShortcutPath (it honours the objective), kept only when the cost goes down and
    every segment stays valid."""
    states = []
    for p in P:
        s = si.allocState()
        s[0:3] = [float(v) for v in p]
        states.append(s)
    path = og.PathGeometric(si, states)
    simplifier = og.PathSimplifier(si, ss.getGoal(), objective)
    best, best_cost = P, problem.path_cost(P)
    for _ in range(10):
        simplifier.partialShortcutPath(path)
        Q = np.array([xyz(s) for s in path.getStates()])
        cost = problem.path_cost(Q)
        if cost < best_cost - 1e-9 and problem.segments_valid(Q[:-1], Q[1:]).all():
            best, best_cost = Q, cost
    return best


def solve_in_workers(problems: list[PlanningProblem]) -> list[PlanResult]:
    """:func:`solve` of each problem in its own fresh process, side by side: the caller's
    threads keep running, and a seed takes effect (OMPL seeds once per process).

    The processes fork from a fork server (forked from one thread: safe with the caller's
    threads), which imports the caller's main module and this one once, where a spawned
    process would import them again (1.4 s of a 5 s plan with the bench as main). A process
    per problem and no pool: a pool that retires its workers after one task spawns their
    replacements, which its shutdown then waits for (2 s on 2 cores)."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["__main__", __name__])
    runs = []
    for problem in problems:
        receive, send = context.Pipe(duplex=False)
        process = context.Process(target=_solve_and_send, args=(problem, send), daemon=True)
        process.start()
        send.close()
        runs.append((process, receive))
    results = []
    try:
        for process, receive in runs:
            try:
                solved, value = receive.recv()
            except EOFError:
                process.join()
                raise RuntimeError(f"the planning process died (exit code {process.exitcode})") from None
            if not solved:
                raise value
            results.append(value)
    finally:
        for process, receive in runs:
            receive.close()
            process.join(timeout=10)
            if process.is_alive():
                process.kill()
    return results


def _solve_and_send(problem: PlanningProblem, send) -> None:
    """A planning process: :func:`solve`, its result (or error) sent back."""
    try:
        send.send((True, solve(problem)))
    except Exception as exc:
        send.send((False, exc))
    finally:
        send.close()
