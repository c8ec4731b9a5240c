"""Planner benchmark on the Paris map, served on 127.0.0.1 (SQLite).

* each planner on one route (the demo's: across the busiest flow of the 1,000-2,500 m band,
  between tube points on either side of it): time to the first solution, cost after 1, 5 and 10 s, motion
  costs and validity checks per second (the Python callbacks are the bottleneck), against
  the optimum of the same cost on the voxel lattice (Dijkstra, 26-connected);
* risk-aware (BIT*, ``--pair-time`` s) against the shortest path over ``--pairs`` random
  start/goal pairs inside the tube, at least 20 km apart: median length increase, median
  integrated-risk decrease.

With ``--directions S``, only this: the Paris map in process (``LocalMap``) with S heading
sectors against the map of one class (today's), both planned (BIT*, hard tube) over the
same random pairs and both routes scored on the directional map: median change of the
conflict exposure (the share of crossing or opposing traffic along the route) and of length.

With ``--vehicle NAME``, only this: the demo's map (its lattice, 8 sectors) in process, and
``--pairs`` random pairs planned for the vehicle (BIT*, hard tube, ``plan_route`` with a
budget of ``--pair-time`` s in all): each risk-aware route as planned (unconstrained) and as
flown (made flyable), the shortest path made flyable, and the route planned in OMPL's
``VanaOwenStateSpace`` instead (BIT*, ``--pair-time`` s of search), scored on the cost map
(cost, length, conflict exposure, max std) and against the vehicle's envelope; the time of
a whole ``plan_route`` (grid, both plans, flyable paths, both judged on the map).

    python bench/bench_planner.py [--pairs 20] [--pair-time 3] [--directions 8 | --vehicle evtol]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_core import rows_table

from bdf.region.route import VEHICLES, envelope
from bdf.region.spec import RegionSpec
from clients import samples
from clients.demo import ROUTE_BAND_M, TUBE_QUANTILE, across_flow, busiest_flow, tube_voxels
from clients.local import LocalService
from clients.sdk import BDFClient
from planner.costmap import CostMap, CostWeights, path_metrics
from planner.dijkstra import lattice_optimum
from planner.routes import LocalMap, plan_route
from planner.search import PLANNERS, PlanningProblem, solve_in_workers

CHECKPOINTS = (1.0, 5.0, 10.0)
NOTE = (
    'The cost columns at 1, 5 and 10 s are the planners\' best before shortcutting; "final cost / lattice" '
    "is the final path (after `partialShortcutPath`) over the lattice optimum; the lattice row's first "
    "column is the Dijkstra time (graph of 26-connected edges, costs vectorised, then search)."
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=20)
    parser.add_argument("--pair-time", type=float, default=3.0)
    parser.add_argument("--directions", type=int, default=0, help="only directional vs one class, S sectors")
    parser.add_argument(
        "--conflict", type=float, default=CostWeights.conflict, help="weight of the conflict term"
    )
    parser.add_argument("--vehicle", choices=sorted(VEHICLES), help="only flyable routes for this vehicle")
    parser.add_argument("--no-append", action="store_true", help="print only, do not append to RESULTS.md")
    args = parser.parse_args()

    obs, lower, upper = samples.load_paris()
    spec = samples.paris_region(lower, upper)
    if args.directions or args.vehicle:
        text = (
            directional_pairs(obs, spec, args) if args.directions else flyable_pairs(obs, lower, upper, args)
        )
        print(text)
        if not args.no_append:
            with open(Path(__file__).with_name("RESULTS.md"), "a") as fh:
                fh.write("\n" + text + "\n")
        return
    with tempfile.TemporaryDirectory() as tmp, LocalService(Path(tmp)) as svc, BDFClient(svc.url) as bdf:
        bdf.create_region(spec)
        bdf.fit(spec.name, obs.X, obs.V, track=obs.flight, t=obs.time)
        grid, bound, P = tube_voxels(bdf, spec)
        step = [float(a[1] - a[0]) for a in grid.axes]
        weights = CostWeights(max_std_mps=bound, cruise_mps=60.0)
        costmap = CostMap(grid.axes, grid.mean, grid.std, weights, known=grid.known)
        centre, direction, flights = busiest_flow(obs, ROUTE_BAND_M)
        a, b = across_flow(P, centre, direction)

        rows = planner_rows(costmap, a, b)
        pairs = pair_rows(bdf, spec, P, weights, step, args)

    report = [
        f"## Planner, {datetime.date.today()}",
        "",
        f"`{' '.join([Path(sys.executable).name, *sys.argv])}` on {platform.machine()}, {os.cpu_count()} "
        f"cores. Paris map (core grid, track-weighted, all flights) served on SQLite; cost map "
        f"{'x'.join(map(str, costmap.shape))} voxels of {step} m over the {ROUTE_BAND_M} m band; tube "
        f"bound {bound:.1f} m/s (the {TUBE_QUANTILE:.0%} quantile of the largest std where there is data); "
        f"cruise 60 m/s, weights risk 1, flow 0.5, hard tube. Route of {np.linalg.norm(b - a) / 1e3:.1f} km "
        f"from {a.round().tolist()} to {b.round().tolist()}, across the busiest flow ({flights} flights "
        f"cross its 2 km cell at {np.round(centre / 1e3, 1).tolist()} km). Each run is a fresh worker "
        "process.",
        "",
        rows_table(rows),
        "",
        NOTE + f" Callbacks take {min(r['callback share'] for r in rows[1:]):.0%}-"
        f"{max(r['callback share'] for r in rows[1:]):.0%} of the time.",
        "",
        pairs,
    ]
    text = "\n".join(report) + "\n"
    print(text)
    if not args.no_append:
        with open(Path(__file__).with_name("RESULTS.md"), "a") as fh:
            fh.write("\n" + text)


def planner_rows(costmap: CostMap, a, b) -> list[dict]:
    problem = PlanningProblem(costmap, tuple(a), tuple(b), seed=1)
    t0 = time.perf_counter()
    reference, _ = lattice_optimum(problem)
    lattice_s = time.perf_counter() - t0
    rows = [
        {
            "planner": "lattice Dijkstra (reference)",
            "first solution s": round(lattice_s, 2),
            "cost 10 s": round(reference),
            "final cost / lattice": 1.0,
        }
    ]
    for name in PLANNERS:
        (sol,) = solve_in_workers(
            [
                PlanningProblem(
                    costmap,
                    tuple(a),
                    tuple(b),
                    planner=name,
                    time_s=max(CHECKPOINTS),
                    checkpoints_s=CHECKPOINTS,
                    seed=1,
                )
            ]
        )
        row = {"planner": name, "first solution s": _round(sol.first_solution_s)}
        for c in CHECKPOINTS:
            cost = sol.cost_at_s.get(c)
            if name == "fmt" and c == max(CHECKPOINTS):  # one-shot: only its final answer
                cost = sol.cost if sol.exact else None
            row[f"cost {c:g} s"] = _round(cost, 0)
        row["final cost / lattice"] = _round(sol.cost / reference if sol.exact else None, 3)
        seconds = max(sol.solve_s, 1e-9)
        row["motion costs /s"] = round(sol.calls["motion_cost"] / seconds)
        row["validity checks /s"] = round((sol.calls["motion_check"] + sol.calls["state_check"]) / seconds)
        row["callback share"] = round(sol.callback_s / seconds, 2)
        row["iterations"] = "-" if sol.iterations is None else sol.iterations
        rows.append(row)
    return rows


def directional_pairs(obs, spec, args) -> str:
    """Directional planning against one class's over random pairs (see the module doc)."""
    weight = obs.track_weights(spec.gamma)
    maps, fit_s = {}, {}
    for S in (1, args.directions):
        t0 = time.perf_counter()
        region = RegionSpec.model_validate({**spec.model_dump(), "directions": S})
        maps[S] = LocalMap.fit(region, obs.X, obs.V, sample_weight=weight)
        fit_s[S] = time.perf_counter() - t0
    grid, bound, P = tube_voxels(maps[1], spec)
    step = [float(a[1] - a[0]) for a in grid.axes]
    weights = CostWeights(max_std_mps=bound, cruise_mps=60.0, conflict=args.conflict)
    rng = np.random.default_rng(0)
    exposure, length, rows, tried = [], [], [], 0
    while len(rows) < args.pairs and tried < 5 * args.pairs:
        tried += 1
        a, b = P[rng.choice(len(P), 2, replace=False)]
        if np.linalg.norm(a - b) < 20_000:
            continue
        plans = {}
        for S, source in maps.items():
            run = dict(
                weights=weights, altitude_m=ROUTE_BAND_M, step=step, time_s=args.pair_time, seed=1 + len(rows)
            )
            plans[S] = plan_route(source, spec.name, a, b, **run)
        if any(p.route is None for p in plans.values()):
            continue
        lanes = plans[args.directions].costmap
        ours, today = (path_metrics(lanes, plans[S].route.enu) for S in (args.directions, 1))
        exposure.append(1 - ours["conflict_exposure"] / max(today["conflict_exposure"], 1e-12))
        length.append(ours["length_m"] / today["length_m"] - 1)
        rows.append((today["conflict_exposure"], ours["conflict_exposure"]))
    today_e, ours_e = np.array(rows).T
    return "\n".join(
        [
            f"## Directional planning, {datetime.date.today()}",
            "",
            f"`{' '.join([Path(sys.executable).name, *sys.argv])}` on {platform.machine()}, {os.cpu_count()} "
            f"cores. Paris (core lattice, all flights, track weights) in process: one class (fit "
            f"{fit_s[1]:.1f} s) and {args.directions} sectors (fit {fit_s[args.directions]:.1f} s). BIT* "
            f"{args.pair_time:g} s per route, hard tube at {bound:.1f} m/s, cruise 60 m/s, conflict weight "
            f"{args.conflict:g}, "
            f"band {ROUTE_BAND_M} m, "
            f"{len(rows)} random pairs in the tube >= 20 km apart ({tried} drawn, pairs where either "
            "planner found no route skipped). Both routes scored on the directional map.",
            "",
            "| | one class (today) | directional |",
            "|---|---|---|",
            f"| median conflict exposure | {np.median(today_e):.3f} | {np.median(ours_e):.3f} |",
            f"| median exposure change, per pair | | {-100 * np.median(exposure):+.1f} % |",
            f"| median length change, per pair | | {100 * np.median(length):+.1f} % "
            f"(max {100 * np.max(length):+.1f} %) |",
        ]
    )


NAMES = ("unconstrained", "flyable", "shortest flyable", "planned in VanaOwen")
SCORES = ("cost_m", "length_m", "conflict_exposure", "max_std_mps", "in_tube_fraction")


def flyable_pairs(obs, lower, upper, args) -> str:
    """Flyable routes for ``args.vehicle`` over random pairs on the demo's map (in process)."""
    spec = samples.paris_demo_region(lower, upper, directions=8)
    t0 = time.perf_counter()
    source = LocalMap.fit(spec, obs.X, obs.V, sample_weight=obs.track_weights(spec.gamma))
    fit_s = time.perf_counter() - t0
    grid, bound, P = tube_voxels(source, spec)
    step = [float(a[1] - a[0]) for a in grid.axes]
    craft = VEHICLES[args.vehicle]
    weights = CostWeights(max_std_mps=bound)
    rng, rows, tried = np.random.default_rng(0), [], 0
    while len(rows) < args.pairs and tried < 5 * args.pairs:
        tried += 1
        a, b = P[rng.choice(len(P), 2, replace=False)]
        if np.linalg.norm(a - b) < 20_000:
            continue
        t0 = time.perf_counter()
        plan = plan_route(
            source, spec.name, a, b, weights=weights, altitude_m=ROUTE_BAND_M, step=step,
            time_s=args.pair_time, seed=1 + len(rows), vehicle=craft,
        )  # fmt: skip
        plan_s = time.perf_counter() - t0
        if plan.route is None:
            continue
        constrained, constrained_s = vana_owen_plan(plan.costmap, a, b, craft, args.pair_time)
        rows.append(_flyable_row(plan, craft, plan_s, constrained, constrained_s))

    def median(name, key, scale=1.0):
        values = [r[(name, key)] for r in rows if (name, key) in r]
        return f"{np.median(values) / scale:.3g}" if values else "-"

    found = sum(("planned in VanaOwen", "cost_m") in r for r in rows)
    table = [
        "| | unconstrained (as planned) | flyable (as flown) | shortest flyable | planned in VanaOwen |",
        "|---|---|---|---|---|",
        f"| routes found | {len(rows)} | {len(rows)} | {len(rows)} | {found} |",
    ]
    within = [
        f"{np.mean([r[(n, 'flyable')] for r in rows if (n, 'flyable') in r] or [np.nan]):.0%}" for n in NAMES
    ]
    table.append(f"| within the envelope | {' | '.join(within)} |")
    for key, label in zip(SCORES, ("cost [km]", "length [km]", "conflict exposure", "max std [m/s]",
                                   "fraction in the tube"), strict=True):  # fmt: skip
        scale = 1e3 if key in ("cost_m", "length_m") else 1.0
        table.append(f"| median {label} | {' | '.join(median(n, key, scale) for n in NAMES)} |")
    least = [min((r[(n, "in_tube_fraction")] for r in rows if (n, "in_tube_fraction") in r), default=np.nan)
             for n in NAMES]  # fmt: skip
    table.append(f"| least fraction in the tube | {' | '.join(f'{v:.3g}' for v in least)} |")
    for key, label in (("cost_m", "cost"), ("length_m", "length")):
        ratio = [r[("flyable", key)] / r[("unconstrained", key)] for r in rows]
        cell = f"{np.median(ratio):.3f} ({np.max(ratio):.3f})"
        table.append(f"| flyable / unconstrained {label}: median (max) | | {cell} | | |")
    with_both = [r for r in rows if ("planned in VanaOwen", "cost_m") in r]
    if with_both:
        ratio = [r[("planned in VanaOwen", "cost_m")] / r[("flyable", "cost_m")] for r in with_both]
        cell = f"{np.median(ratio):.3f} ({np.max(ratio):.3f})"
        table.append(f"| VanaOwen / flyable cost, where both: median (max) | | | | {cell} |")
    planned_s = [r["VanaOwen s"] for r in rows]
    times = [r["plan s"] for r in rows]
    command = " ".join([Path(sys.executable).name, *sys.argv])
    return "\n".join(
        [
            f"## Flyable routes, {datetime.date.today()}",
            "",
            f"`{command}` on {platform.machine()}, {os.cpu_count()} cores. The demo's map in process "
            f"(8 sectors, fit {fit_s:.0f} s); {len(rows)} random pairs in the tube >= 20 km apart ({tried} "
            f"drawn); plan_route's budget {args.pair_time:g} s per route, hard tube at {bound:.1f} m/s, "
            "vehicle "
            f"{args.vehicle}: {craft}. All paths scored on the plan's cost map.",
            "",
            *table,
            "",
            "`plan_route` per pair (grid, both plans in parallel, flyable paths, both judged on the map): "
            f"median {np.median(times):.1f} s, max {np.max(times):.1f} s. Planning in `VanaOwenStateSpace` "
            f"(BIT* {args.pair_time:g} s, a plain objective integrating the cost map along each curved "
            f"motion, in this process after plan_route): median {np.median(planned_s):.1f} s. The lattice "
            "optimum of this directional cost does not fit in memory at this grid (26-connected edges x 9 "
            "classes); it stays the reference of the unconstrained cost on the one-class map (the planners' "
            "table of this bench).",
        ]
    )


def vana_owen_plan(costmap: CostMap, a, b, craft, time_s: float) -> tuple[np.ndarray | None, float]:
    """The risk-aware route planned in OMPL's ``VanaOwenStateSpace`` (curvature- and
    pitch-constrained Dubins-airplane paths, docs/ompl.md section 10): BIT* with a plain
    ``OptimizationObjective`` (the PathLength subclass's informed sampler refuses this space)
    whose motion cost integrates the cost map along the curved motion (``interpolate``), the
    hard tube checked at the same points, start and goal headed along their chord. Returns
    the path interpolated every 50 m (None if none found) and the wall time."""
    from ompl import base as ob
    from ompl import geometric as og
    from ompl import util as ou

    ou.setLogLevel(ou.LOG_ERROR)
    t0 = time.perf_counter()
    pitch = np.radians(min(craft.max_climb_deg, craft.max_descent_deg))
    space = ob.VanaOwenStateSpace(craft.min_turn_radius_m, float(pitch))
    bounds = ob.RealVectorBounds(3)
    lower, upper = costmap.lower, costmap.upper
    bounds.low = [float(v) for v in lower]
    bounds.high = [float(v) for v in upper]
    space.setBounds(bounds)
    ss = og.SimpleSetup(space)
    si = ss.getSpaceInformation()
    bound = costmap.weights.max_std_mps
    scratch = space.allocState()

    def along(s1, s2) -> np.ndarray:
        n = max(int(space.distance(s1, s2) / costmap.sample_m), 1) + 1
        out = np.empty((n, 3))
        for i, t in enumerate(np.linspace(0.0, 1.0, n)):
            space.interpolate(s1, s2, float(t), scratch)
            out[i] = scratch[0], scratch[1], scratch[2]
        return out

    class Checker(ob.StateValidityChecker):
        def isValid(self, s):
            inside = all(lower[d] <= s[d] <= upper[d] for d in range(3))
            return inside and bool(costmap.max_std_high(np.array([[s[0], s[1], s[2]]]))[0] <= bound)

    class Motions(ob.MotionValidator):
        def checkMotion(self, s1, s2):
            P = along(s1, s2)
            if np.any(P < lower) or np.any(P > upper):
                return False
            return bool(costmap.segments_in_tube(P[:-1], P[1:]).all())

    class Objective(ob.OptimizationObjective):
        def stateCost(self, s):
            return ob.Cost(0.0)

        def motionCost(self, s1, s2):
            P = along(s1, s2)
            return ob.Cost(float(costmap.segment_costs(P[:-1], P[1:]).sum()))

    checker, motions = Checker(si), Motions(si)
    ss.setStateValidityChecker(checker)
    si.setMotionValidator(motions)
    ss.setOptimizationObjective(Objective(si))
    heading = float(np.arctan2(b[1] - a[1], b[0] - a[0]))  # yaw: from the x axis
    start, goal = space.allocState(), space.allocState()
    for state, p in ((start, a), (goal, b)):
        state[0], state[1], state[2] = (float(v) for v in p)
        state.setYaw(heading)
    ss.setStartAndGoalStates(start, goal, 1.0)
    ss.setPlanner(og.BITstar(si))
    ss.solve(time_s)
    if not ss.haveExactSolutionPath():
        return None, time.perf_counter() - t0
    path = og.PathGeometric(ss.getSolutionPath())
    path.interpolate(max(int(path.length() / 50.0), 2))
    P = np.array([[s[0], s[1], s[2]] for s in path.getStates()])
    keep = np.concatenate([[True], np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-6])
    return P[keep], time.perf_counter() - t0


def _flyable_row(plan, craft, plan_s, constrained, constrained_s) -> dict:
    """One pair's paths scored on the plan's cost map and against the envelope."""
    cm = plan.costmap
    found = (plan.route.planned, plan.route.enu, plan.baseline.enu, constrained)
    paths = dict(zip(NAMES, found, strict=True))
    if constrained is None:
        del paths["planned in VanaOwen"]
    row = {"plan s": plan_s, "VanaOwen s": constrained_s}
    for name, path in paths.items():
        m = path_metrics(cm, path)
        row |= {(name, k): m[k] for k in SCORES}
        row[(name, "flyable")] = envelope(path, craft)["flyable"]
    return row


def _round(value, digits=2):
    return "-" if value is None or not np.isfinite(value) else round(value, digits)


def pair_rows(bdf, spec, P, weights, step, args) -> str:
    rng = np.random.default_rng(0)
    length_up, risk_down, std_ratio, found = [], [], [], 0
    tried = 0
    while found < args.pairs and tried < 5 * args.pairs:
        tried += 1
        a, b = P[rng.choice(len(P), 2, replace=False)]
        if np.linalg.norm(a - b) < 20_000:
            continue
        plan = plan_route(
            bdf,
            spec.name,
            a,
            b,
            weights=weights,
            altitude_m=ROUTE_BAND_M,
            step=step,
            time_s=args.pair_time,
            seed=1 + found,
        )
        if plan.route is None:
            continue
        found += 1
        r, s = plan.route.metrics, plan.baseline.metrics
        length_up.append(r["length_m"] / s["length_m"] - 1)
        risk_down.append(1 - r["integrated_risk_m"] / s["integrated_risk_m"])
        std_ratio.append(r["max_std_mps"] / weights.max_std_mps)
    return (
        f"Risk-aware (BIT*, {args.pair_time:g} s) vs shortest over {found} random pairs in the tube "
        f"(>= 20 km apart, {tried} drawn): median length +{100 * np.median(length_up):.1f} % "
        f"(max +{100 * np.max(length_up):.1f} %), median integrated risk -{100 * np.median(risk_down):.1f} % "
        f"(min -{100 * np.min(risk_down):.1f} %). The service's std every 10 m along the risk-aware "
        f"routes (hard tube): at most {np.max(std_ratio):.3f} of the bound (median of the maxima "
        f"{np.median(std_ratio):.3f}); {sum(r > 1 for r in std_ratio)} of {found} routes leave the tube."
    )


if __name__ == "__main__":
    main()
