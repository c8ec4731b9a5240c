"""Plan a risk-aware route and its shortest-path baseline on a region's map.

The map comes from any :class:`MapSource`: the SDK's client over HTTP, or a region in
process (:class:`LocalMap`). One grid request fetches mean and std (and, for a directional
region, every traffic class's modes) for the planning box; both routes are planned in
fresh worker processes (OMPL holds the GIL and seeds once per process); each route is then
judged on the map itself, as any route is (:func:`bdf.region.route.assess`: the service's
``routes/assess``): std of the mode flown every 10 m, tube, risk, conflict, flow, envelope.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from bdf.region.evidence import increments, region_total
from bdf.region.map import RegionMap, compute_posterior
from bdf.region.route import VEHICLES, Vehicle, times_at
from bdf.region.route import assess as assess_on_map
from bdf.region.route import vehicle as as_vehicle  # plan_route's argument is named vehicle
from bdf.region.spec import RegionSpec
from planner.costmap import CostMap, CostWeights, ModeGrids
from planner.flyable import flyable
from planner.search import Box, PlanningProblem, PlanResult, solve_in_workers

log = logging.getLogger(__name__)
MAX_VOXELS = 400_000
#: A plan's budget by default (s): the grid, both plans side by side, the flyable paths and
#: both judged on the map (bench_planner.py measures it).
PLAN_TIME_S = 5.0
#: What a plan keeps of its budget for judging both routes on the map after the planners (s).
JUDGE_S = 0.3
#: A hard-tube route the service finds above the bound is planned again on a grid of half
#: the step, at most this many times (and while the grid stays within 4 x MAX_VOXELS).
REFINES = 2


class MapSource(Protocol):
    """What the planner asks of a map: the SDK's ``BDFClient`` has these methods."""

    def region(self, name: str) -> Any:
        """An object with the region's ``spec``."""

    def grid(self, name: str, step, bbox=None, *, modes: bool = False) -> Any:
        """An object with ``axes``, ``mean``, ``std``, ``known`` and, with ``modes``,
        ``share``, ``mode_mean``, ``mode_std``, ``mode_heading_noise`` (as
        :meth:`clients.sdk.BDFClient.grid`)."""

    def assess_route(self, name: str, route, *, max_std_mps: float, vehicle: dict, times_s) -> dict:
        """A route's metrics on the map (as :meth:`clients.sdk.BDFClient.assess_route`)."""


@dataclass(frozen=True)
class LocalRegion:
    spec: RegionSpec


@dataclass(frozen=True)
class LocalGrid:
    axes: tuple[np.ndarray, np.ndarray, np.ndarray]
    mean: np.ndarray
    std: np.ndarray
    known: np.ndarray
    share: np.ndarray | None = None
    mode_mean: np.ndarray | None = None
    mode_std: np.ndarray | None = None
    share_std: np.ndarray | None = None
    mode_heading_noise: np.ndarray | None = None

    @property
    def x(self) -> np.ndarray:
        return self.axes[0]

    @property
    def y(self) -> np.ndarray:
        return self.axes[1]

    @property
    def z(self) -> np.ndarray:
        return self.axes[2]


class LocalMap:
    """A region's map in process, as a :class:`MapSource`: the spec and its posterior
    (:func:`bdf.region.map.compute_posterior`)."""

    def __init__(self, spec: RegionSpec, posterior):
        self.spec, self.map = spec, RegionMap(spec, posterior)

    @classmethod
    def fit(cls, spec: RegionSpec, X, V, **kwargs) -> LocalMap:
        """The map of observations ``(X, V)`` (keywords of :func:`bdf.region.evidence.increments`)."""
        tile_increments = increments(spec, X, V, **kwargs)
        evidence = region_total(spec, {k: i.evidence for k, i in tile_increments.items()})
        return cls(spec, compute_posterior(spec, evidence))

    def _check(self, name: str) -> None:
        if name != self.spec.name:
            raise ValueError(f"this map holds region {self.spec.name!r}, not {name!r}")

    def region(self, name: str) -> LocalRegion:
        self._check(name)
        return LocalRegion(self.spec)

    def grid(self, name: str, step, bbox=None, *, modes: bool = False) -> LocalGrid:
        self._check(name)
        lo, hi = (self.spec.lower, self.spec.upper) if bbox is None else (bbox[:3], bbox[3:])
        axes = tuple(self.spec.box_axes(lo, hi, step))
        m = self.map.predict_grid_modes(axes) if modes else None
        mean, std, known = self.map.predict_grid(axes, m)
        if m is None:
            return LocalGrid(axes, mean, std, known)
        return LocalGrid(axes, mean, std, known, m.share, m.mean, m.std, m.share_std, m.heading_noise)

    def assess_route(self, name: str, route, *, max_std_mps: float, vehicle: dict, times_s) -> dict:
        self._check(name)
        craft = Vehicle(**vehicle)
        return assess_on_map(self.map, route, max_std_mps=max_std_mps, craft=craft, times_s=times_s)


@dataclass
class Route:
    """One route: the path flown in region ENU and WGS84 (lat, lon, alt_m), the time at each
    of its points (s from departure, at the cruise airspeed), its metrics, and with a vehicle
    its envelope's verdict (:func:`bdf.region.route.envelope`) and the polyline the planner
    found before it was made flyable (:func:`planner.flyable.flyable`)."""

    name: str
    enu: np.ndarray
    wgs84: np.ndarray
    times_s: np.ndarray
    metrics: dict[str, float]
    solution: PlanResult | None  # None for the straight line
    planned: np.ndarray
    envelope: dict | None = None
    planned_max_std_mps: float = 0.0  # the service's std along the planned polyline


@dataclass
class RoutePlan:
    region: RegionSpec
    costmap: CostMap
    route: Route | None  # None when the planner found no path in the budget
    baseline: Route
    status: str

    def geojson(self) -> dict:
        """Both routes as GeoJSON LineStrings ([lon, lat, alt_m]) with their ``metrics``, the
        time at each point (``times_s``, seconds from departure, the convention of
        ``coordTimes`` in seconds), the plan's tube bound (``max_std_mps``: what
        ``routes/assess`` reads, so assessing a route of the file gives the plan's own
        figures) and the envelope's verdict."""
        features = []
        for r in (self.route, self.baseline):
            if r is None:
                continue
            coordinates = [[lon, lat, alt] for lat, lon, alt in r.wgs84.tolist()]
            properties = {
                "name": r.name,
                "region": self.region.name,
                "metrics": r.metrics,
                "max_std_mps": self.costmap.weights.max_std_mps,
                "times_s": r.times_s.tolist(),
            }
            if r.envelope is not None:
                properties["envelope"] = r.envelope
            if r.solution is not None:
                properties.update(planner_status=r.solution.status, solve_s=r.solution.solve_s)
            features.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "LineString", "coordinates": coordinates},
                    "properties": properties,
                }
            )
        return {"type": "FeatureCollection", "features": features}

    def table(self) -> str:
        """The two routes' metrics side by side."""
        rows = [
            (k, self.route.metrics.get(k) if self.route else None, self.baseline.metrics[k])
            for k in self.baseline.metrics
        ]
        if self.baseline.envelope is not None:
            for key, value in self.baseline.envelope.items():
                mine = self.route.envelope.get(key) if self.route else None
                rows.append((f"envelope: {key}", mine, value))
        width = max(len(k) for k, *_ in rows)
        lines = [f"{'':<{width}}  {'risk-aware':>12}  {'shortest':>12}"]
        for key, a, b in rows:
            lines.append(f"{key:<{width}}  {_cell(a):>12}  {_cell(b):>12}")
        return "\n".join(lines)


def _cell(value) -> str:
    if value is None:
        return "-"
    return str(value) if isinstance(value, bool) else f"{value:12.4g}"


def planning_box(spec: RegionSpec, start, goal, altitude_m, margin_m: float | None):
    """The box around start and goal (plus ``margin_m``, default 30 % of their distance and at
    least two hinge spacings), clipped to the region; altitude from the band."""
    start, goal = np.asarray(start, float), np.asarray(goal, float)
    if margin_m is None:
        margin_m = max(0.3 * float(np.linalg.norm(goal[:2] - start[:2])), 2 * max(spec.spacing_m[:2]))
    lo = np.minimum(start, goal) - margin_m
    hi = np.maximum(start, goal) + margin_m
    lo[2], hi[2] = (spec.lower[2], spec.upper[2]) if altitude_m is None else altitude_m
    lo, hi = np.maximum(lo, spec.lower), np.minimum(hi, spec.upper)
    if np.any(hi <= lo):
        raise ValueError(
            f"the planning box {lo.tolist()} .. {hi.tolist()} is empty inside region {spec.name!r}"
        )
    return lo, hi


def grid_step(spec: RegionSpec, lo, hi, step=None, max_voxels: int = MAX_VOXELS) -> np.ndarray:
    """A quarter of the hinge spacing (the field varies on that scale), coarsened evenly until
    the grid has at most ``max_voxels``."""
    if step is not None:
        step = np.broadcast_to(np.asarray(step, float), (3,)).copy()
        if not (step > 0).all():
            raise ValueError(f"step must be positive, got {step.tolist()}")
        return step
    step = np.asarray(spec.spacing_m, float) / 4
    while np.prod(np.floor((hi - lo) / step) + 1) > max_voxels:
        step *= 1.25
    return step


def _to_enu(spec: RegionSpec, p, frame: str) -> np.ndarray:
    p = np.asarray(p, float)
    if p.shape != (3,):
        raise ValueError(f"a point needs 3 coordinates, got {p.tolist()}")
    if frame == "enu":
        return p
    if frame != "wgs84":
        raise ValueError(f"frame must be 'enu' or 'wgs84', got {frame!r}")
    return spec.frame().to_enu(p[:1], p[1:2], p[2:])[0]


def plan_route(
    client: MapSource,
    region: str,
    start,
    goal,
    *,
    weights: CostWeights,
    frame: str = "enu",
    altitude_m: tuple[float, float] | None = None,
    no_fly: tuple[Box, ...] = (),
    step=None,
    margin_m: float | None = None,
    planner: str = "bitstar",
    time_s: float = PLAN_TIME_S,
    seed: int | None = None,
    max_iterations: int | None = None,
    vehicle: Vehicle | str | None = None,
) -> RoutePlan:
    """Plan the risk-aware route from ``start`` to ``goal`` (ENU metres, or lat, lon, alt_m
    with ``frame="wgs84"``) and the shortest path, and measure both.

    With the hard tube, the service's std along the route is the judge: a route that
    rises above the bound between grid nodes is planned again on a grid of half the step
    (up to ``REFINES`` times); the last plan is returned, with a warning if it still does.

    ``time_s``: each attempt's budget, from the grid request to both routes judged: the
    planners stop in time for it (their processes' start counts); with ``max_iterations``
    they run that many iterations instead.

    ``vehicle`` (a :class:`~bdf.region.route.Vehicle` or its name): both routes are made
    flyable by it (:func:`planner.flyable.flyable`), timed at its cruise airspeed, which the
    cost's flow and conflict terms use too, and checked against its envelope; without one
    they are the planner's polylines, timed at ``weights.cruise_mps``.
    """
    craft = None if vehicle is None else as_vehicle(vehicle)
    if craft is not None:
        weights = dataclasses.replace(weights, cruise_mps=craft.cruise_mps)
    spec = RegionSpec.model_validate(client.region(region).spec)
    start, goal = _to_enu(spec, start, frame), _to_enu(spec, goal, frame)
    box = planning_box(spec, start, goal, altitude_m, margin_m)
    if craft is not None:  # it flies inside the planning box's altitudes too
        floor, ceiling = max(craft.floor_m, box[0][2]), min(craft.ceiling_m, box[1][2])
        if floor >= ceiling:
            raise ValueError(
                f"the vehicle flies between {craft.floor_m:g} and {craft.ceiling_m:g} m, the planning band "
                f"is {box[0][2]:g} .. {box[1][2]:g} m (region ENU): they do not overlap"
            )
        craft = dataclasses.replace(craft, floor_m=floor, ceiling_m=ceiling)
    step = grid_step(spec, *box, step)
    # the planner settings of every attempt: PlanningProblem's keyword arguments
    run = dict(no_fly=tuple(no_fly), planner=planner, time_s=time_s, max_iterations=max_iterations, seed=seed)
    for refine in range(REFINES + 1):
        plan = _plan_on_grid(client, region, spec, start, goal, box, step, weights, run, craft)
        bound, route = weights.max_std_mps, plan.route
        if weights.tube != "hard" or route is None or route.planned_max_std_mps <= bound:
            return plan
        finer = step / 2
        too_big = np.prod(np.floor((box[1] - box[0]) / finer) + 1) > 4 * MAX_VOXELS
        log.warning(
            "the route leaves the tube between grid nodes (service std %.3g > %.3g m/s)%s",
            route.planned_max_std_mps,
            bound,
            "" if refine == REFINES or too_big else f": planning again with a step of {finer.tolist()} m",
        )
        if too_big:
            break
        step = finer
    return plan


def _plan_on_grid(client, region, spec, start, goal, box, step, weights, run, craft) -> RoutePlan:
    """One grid request, the two plans on it (worker processes), both routes measured, within
    ``run["time_s"]``."""
    deadline = time.time() + run["time_s"] - JUDGE_S
    lo, hi = box[0].copy(), box[1]
    # on the region's lattice of this step: the same voxels as any other grid of the step
    lo[:2] = spec.lower[:2] + np.floor((lo[:2] - spec.lower[:2]) / step[:2] + 1e-9) * step[:2]
    directional = not spec.one_class
    grid = client.grid(region, step, bbox=[*lo, *hi], modes=directional)
    modes = None
    if directional:
        modes = ModeGrids(grid.share, grid.mode_mean, grid.mode_std, grid.mode_heading_noise, spec.sectors)
    costmap = CostMap(grid.axes, grid.mean, grid.std, weights, known=grid.known, modes=modes)
    # the grid ends on a whole step: the box the planner sees is the grid's
    band = (float(costmap.lower[2]), float(costmap.upper[2]))
    risk = PlanningProblem(costmap, tuple(start), tuple(goal), band, deadline=deadline, **run)
    shortest = dataclasses.replace(risk, objective="length")
    straight = shortest.segments_valid(start[None], goal[None])[0]
    solution, *rest = solve_in_workers([risk] if straight else [risk, shortest])
    short = rest[0] if rest else None
    baseline_path = np.array([start, goal]) if straight else short.waypoints
    if len(baseline_path) < 2:
        raise ValueError(
            f"no path from {start.tolist()} to {goal.tolist()} avoids the no-fly boxes "
            f"within {run['time_s']} s ({short.status})"
        )
    route, status = None, solution.status
    measure = (client, region, spec, costmap, craft)
    if solution.exact:
        route = _route("risk-aware", solution.waypoints, solution, *measure, kept_in_tube=risk.hard_tube)
    elif straight:  # the budget ran out, but the straight line is a route (in the tube, if hard)
        route = _route("risk-aware", np.array([start, goal]), None, *measure, kept_in_tube=risk.hard_tube)
        status = f"{solution.status}: the straight line, valid for the plan, is the route"
    baseline = _route("shortest", baseline_path, short, *measure)
    return RoutePlan(spec, costmap, route, baseline, status)


def _route(name, planned, solution, client, region, spec, costmap, craft, kept_in_tube=False) -> Route:
    """The route flown (the planned polyline, made flyable by ``craft`` if given; with
    ``kept_in_tube``, in the tube the planner kept to), judged on the map as any route is
    (``assess_route``; the envelope's verdict kept with a vehicle), and its cost on the plan's
    cost map (the planner's objective)."""
    tube = costmap.segments_in_tube if kept_in_tube else None
    P = planned if craft is None else flyable(planned, craft, in_tube=tube)
    cruise = costmap.weights.cruise_mps
    times_s = times_at(P, cruise)
    judge = dict(max_std_mps=costmap.weights.max_std_mps, vehicle=dataclasses.asdict(craft or _TIMED))
    judged = client.assess_route(region, P, times_s=times_s, **judge)
    metrics = {"cost_m": float(costmap.segment_costs(P[:-1], P[1:]).sum()), **judged["total"]}
    if craft is not None:
        before = client.assess_route(region, planned, times_s=times_at(planned, cruise), **judge)
    return Route(
        name,
        P,
        spec.frame().to_geodetic(P),
        times_s,
        metrics,
        solution,
        planned,
        None if craft is None else judged["envelope"],
        metrics["max_std_mps"] if craft is None else before["total"]["max_std_mps"],
    )


#: The vehicle a route planned without one is judged with: its times are given, its envelope
#: is not reported.
_TIMED = VEHICLES["evtol"]
