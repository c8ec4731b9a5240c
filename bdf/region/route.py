"""A route judged against a region's map and a vehicle: the metrics the planner and the
service share.

A route is a polyline in region ENU metres, flown from its first point to its last, with
times (seconds from departure) or at a cruise airspeed. :func:`assess` samples each segment
every ``sample_m`` (the midpoint of each piece) and reads the map there: the predictive
std of the mode of the heading flown (on a directional map; the map's one mode otherwise),
the share of traffic crossing or opposing that heading, and that mode's mean velocity
against the route's. :func:`envelope` says whether a vehicle can fly the polyline as it
is: its turns, its climbs and descents, its altitudes.

The turn radius is read every ``sample_m`` along the route as the radius of the circle
through the points ``TURN_WINDOW_M`` before and after each sample (three points on an arc
of radius R give R exactly; a corner gives a radius of the order of the window).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bdf.region.map import RegionMap
from bdf.sectors import CROSSING_DEG
from bdf.validation import as_points

#: Most points a route may have (the service's limit too).
MAX_ROUTE_POINTS = 20_000
#: A route is sampled this often (metres) for its metrics and its envelope.
SAMPLE_M = 10.0
#: Half the chord over which a turn's radius is measured (metres).
TURN_WINDOW_M = 50.0
#: The envelope holds to within this fraction (discretised arcs and rounding).
ENVELOPE_TOLERANCE = 0.02


@dataclass(frozen=True)
class Vehicle:
    """What a vehicle can fly: cruise airspeed (m/s), the least turn radius (m), the
    steepest climb and descent (degrees of flight-path angle), and the altitudes it flies
    between (region ENU metres)."""

    cruise_mps: float
    min_turn_radius_m: float
    max_climb_deg: float
    max_descent_deg: float
    floor_m: float
    ceiling_m: float

    def __post_init__(self):
        for name in (
            "cruise_mps",
            "min_turn_radius_m",
            "max_climb_deg",
            "max_descent_deg",
            "floor_m",
            "ceiling_m",
        ):
            object.__setattr__(self, name, float(getattr(self, name)))  # plain floats: JSON, equality
        for name in ("cruise_mps", "min_turn_radius_m"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        for name in ("max_climb_deg", "max_descent_deg"):
            if not 0 < getattr(self, name) < 90:
                raise ValueError(f"{name} must be in (0, 90) degrees, got {getattr(self, name)!r}")
        if not (np.isfinite(self.floor_m) and np.isfinite(self.ceiling_m) and self.floor_m < self.ceiling_m):
            raise ValueError(f"floor_m {self.floor_m!r} must be below ceiling_m {self.ceiling_m!r}")


#: Defaults: an eVTOL in wing-borne cruise (60 m/s, a 25-degree bank: R = v^2 / (g tan 25)
#: = 790 m) and a light fixed-wing aircraft (60 m/s, a 30-degree bank: 640 m; a climb of
#: 3.5 m/s at 40 m/s).
VEHICLES = {
    "evtol": Vehicle(60.0, 800.0, 8.0, 8.0, 300.0, 3000.0),
    "fixed-wing": Vehicle(60.0, 650.0, 5.0, 6.0, 300.0, 4000.0),
}


def vehicle(value: str | dict | Vehicle) -> Vehicle:
    """A :class:`Vehicle` from its name in :data:`VEHICLES`, its fields, or itself."""
    if isinstance(value, Vehicle):
        return value
    if isinstance(value, str):
        if value not in VEHICLES:
            raise ValueError(f"unknown vehicle {value!r}; known: {sorted(VEHICLES)}")
        return VEHICLES[value]
    return Vehicle(**{k: float(v) for k, v in dict(value).items()})


def as_route(P, name: str = "route") -> np.ndarray:
    """(n, 3) finite points, 2 to :data:`MAX_ROUTE_POINTS`, no two consecutive ones equal."""
    P = as_points(P, name)
    if not 2 <= len(P) <= MAX_ROUTE_POINTS:
        raise ValueError(f"a {name} needs 2 to {MAX_ROUTE_POINTS} points, got {len(P)}")
    if np.any(np.linalg.norm(np.diff(P, axis=0), axis=1) == 0):
        raise ValueError(f"{name} has two consecutive points that are the same")
    return P


def resample(P: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points every ``spacing_m`` of 3-D length along the polyline, its ends included."""
    length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    s = np.append(np.arange(0.0, length[-1], spacing_m), length[-1])
    return np.stack([np.interp(s, length, P[:, d]) for d in range(3)], axis=1)


def turn_radii(P: np.ndarray, sample_m: float = SAMPLE_M, window_m: float = TURN_WINDOW_M) -> np.ndarray:
    """The horizontal turn radius (m) at each sample every ``sample_m`` along ``P``: the
    circle through the samples ``window_m`` before and after it (inf on a straight line)."""
    Q = resample(P, sample_m)[:, :2]
    k = max(round(window_m / sample_m), 1)
    if len(Q) < 2 * k + 1:
        return np.full(0, np.inf)
    a, b, c = Q[: -2 * k], Q[k:-k], Q[2 * k :]
    ab, bc, ca = (np.linalg.norm(u - v, axis=1) for u, v in ((a, b), (b, c), (c, a)))
    cross = np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    with np.errstate(divide="ignore"):
        return np.where(cross > 1e-9 * ab * bc, ab * bc * ca / (2.0 * cross), np.inf)


def envelope(P, craft: Vehicle, sample_m: float = SAMPLE_M, tolerance: float = ENVELOPE_TOLERANCE) -> dict:
    """Whether ``craft`` can fly the polyline ``P`` as it is: the least turn radius (None
    where it never turns), the steepest climb and descent (per ``sample_m`` of it), the
    lowest and highest altitude, and for each limit whether it holds (within ``tolerance``).
    A small vehicle's turns are read over shorter chords (:data:`TURN_WINDOW_M`, at most a
    quarter of its turn radius, sampled three times as often)."""
    P = as_route(P)
    window = min(TURN_WINDOW_M, craft.min_turn_radius_m / 4)  # within the arc of a 30-degree turn
    sample_m = min(sample_m, window / 3)
    Q = resample(P, sample_m)
    step = np.diff(Q, axis=0)
    angle = np.degrees(np.arctan2(step[:, 2], np.hypot(step[:, 0], step[:, 1])))
    radius = float(np.min(turn_radii(P, sample_m, window), initial=np.inf))
    out = {
        "min_turn_radius_m": radius if np.isfinite(radius) else None,  # None: it never turns
        "max_climb_deg": float(max(angle.max(), 0.0)),
        "max_descent_deg": float(max(-angle.min(), 0.0)),
        "min_alt_m": float(Q[:, 2].min()),
        "max_alt_m": float(Q[:, 2].max()),
    }
    slack = 1.0 + tolerance
    checks = {
        "turn_ok": bool(radius * slack >= craft.min_turn_radius_m),
        "climb_ok": bool(out["max_climb_deg"] <= craft.max_climb_deg * slack),
        "descent_ok": bool(out["max_descent_deg"] <= craft.max_descent_deg * slack),
        "altitude_ok": bool(
            out["min_alt_m"] >= craft.floor_m - 1.0 and out["max_alt_m"] <= craft.ceiling_m + 1.0
        ),
    }
    return {**out, **checks, "flyable": all(checks.values())}


def times_at(P: np.ndarray, cruise_mps: float) -> np.ndarray:
    """Seconds from departure at each point, flying the polyline at ``cruise_mps``."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))]) / cruise_mps


def checked(P, craft: Vehicle, times_s=None, heading_deg=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A route's points (:func:`as_route`), its times (by default at the vehicle's cruise
    airspeed; increasing, one per point) and the heading flown on each segment (degrees from
    north, clockwise; by default its own direction): ``ValueError`` says what is wrong."""
    P = as_route(P)
    times = times_at(P, craft.cruise_mps) if times_s is None else np.asarray(times_s, float).ravel()
    if times.shape != (len(P),) or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise ValueError(f"times_s must be {len(P)} finite, increasing seconds, one per point")
    delta = np.diff(P, axis=0)
    if heading_deg is None:
        return P, times, np.degrees(np.arctan2(delta[:, 0], delta[:, 1])) % 360.0
    heading = np.asarray(heading_deg, float).ravel()
    if heading.shape != (len(P) - 1,) or not np.all(np.isfinite(heading)):
        raise ValueError(f"heading_deg must be {len(P) - 1} finite degrees, one per segment")
    return P, times, heading


def assess(
    region_map: RegionMap,
    P,
    *,
    max_std_mps: float,
    craft: Vehicle,
    times_s=None,
    heading_deg=None,
    sample_m: float = SAMPLE_M,
) -> dict:
    """The metrics of route ``P`` (n, 3, region ENU) on the map, per segment and in total.

    ``times_s`` (n,): when each point is passed (increasing); by default at the vehicle's
    cruise airspeed. ``heading_deg`` (n - 1,): the heading flown on each segment (degrees
    from north, clockwise; by default its own direction), which picks the mode on a
    directional map. Per segment and in total: length, duration, the max and the
    length-weighted mean of the std (the largest of the three components, of the mode
    flown), the fraction of the length inside the tube ``std <= max_std_mps``, the risk
    ``∫ std / max_std_mps ds`` (metres), the conflict exposure (the length-weighted mean
    share of traffic in sectors at least :data:`~bdf.sectors.CROSSING_DEG` off the heading;
    0 on a map of one class) and the flow mismatch (the length-weighted mean of
    ``|route velocity - mean of the mode flown|``, m/s), split into its direction (the mean
    angle between the route's heading and the mode's, degrees) and the mode's horizontal
    speed (a route flying with traffic much faster than itself has a large mismatch at no
    angle); and the envelope's verdict.
    """
    spec = region_map.spec
    P, times_s, heading = checked(P, craft, times_s, heading_deg)
    outside = np.flatnonzero(~spec.inside(P))
    if len(outside):
        raise ValueError(f"route points {outside[:5].tolist()} are outside region {spec.name!r}")
    if not (np.isfinite(max_std_mps) and max_std_mps > 0):
        raise ValueError(f"max_std_mps must be positive, got {max_std_mps!r}")
    n_seg = len(P) - 1
    delta = np.diff(P, axis=0)
    length = np.linalg.norm(delta, axis=1)
    velocity = delta / np.diff(times_s)[:, None]
    pieces = np.maximum(np.ceil(length / sample_m).astype(int), 1)
    seg = np.repeat(np.arange(n_seg), pieces)
    within = (np.arange(len(seg)) - np.repeat(np.cumsum(pieces) - pieces, pieces) + 0.5) / pieces[seg]
    X = P[seg] + within[:, None] * delta[seg]
    ds = length[seg] / pieces[seg]
    sectors = spec.sectors
    modes = region_map.predict_modes(X)
    if sectors.classes == 1:
        flown = np.zeros(len(X), np.int64)
    else:
        speed = np.hypot(velocity[seg, 0], velocity[seg, 1])
        sector = sectors.sector_of_heading(heading[seg])
        flown = np.where(speed < sectors.slow_mps, sectors.directions, sector)
    rows = np.arange(len(X))
    std = modes.std[rows, flown].max(axis=1)
    traffic = modes.mean[rows, flown]
    mismatch = np.linalg.norm(velocity[seg] - traffic, axis=1)
    traffic_heading = np.degrees(np.arctan2(traffic[:, 0], traffic[:, 1]))
    offset = np.abs((traffic_heading - heading[seg] + 180.0) % 360.0 - 180.0)
    traffic_speed = np.hypot(traffic[:, 0], traffic[:, 1])
    if sectors.classes == 1:
        crossing = np.zeros(len(X))
    else:
        off = np.abs((sectors.centres_deg[None, :] - heading[seg, None] + 180.0) % 360.0 - 180.0)
        crossing = (modes.share[:, : sectors.directions] * (off >= CROSSING_DEG)).sum(axis=1)

    def per_segment(values):
        return np.bincount(seg, weights=values * ds, minlength=n_seg)

    def maxima(values):
        out = np.full(n_seg, -np.inf)
        np.maximum.at(out, seg, values)
        return out

    inside = (std <= max_std_mps).astype(float)
    segments = {
        "length_m": length,
        "duration_s": np.diff(times_s),
        "max_std_mps": maxima(std),
        "mean_std_mps": per_segment(std) / length,
        "in_tube_fraction": per_segment(inside) / length,
        "integrated_risk_m": per_segment(std / max_std_mps),
        "conflict_exposure": per_segment(crossing) / length,
        "flow_mismatch_mps": per_segment(mismatch) / length,
        "flow_heading_offset_deg": per_segment(offset) / length,
        "traffic_speed_mps": per_segment(traffic_speed) / length,
    }
    total_length = float(length.sum())
    totals = {
        "length_m": total_length,
        "duration_s": float(times_s[-1] - times_s[0]),
        "max_std_mps": float(std.max()),
        "mean_std_mps": float((std * ds).sum() / total_length),
        "in_tube_fraction": float((inside * ds).sum() / total_length),
        "integrated_risk_m": float((std / max_std_mps * ds).sum()),
        "conflict_exposure": float((crossing * ds).sum() / total_length),
        "flow_mismatch_mps": float((mismatch * ds).sum() / total_length),
        "flow_heading_offset_deg": float((offset * ds).sum() / total_length),
        "traffic_speed_mps": float((traffic_speed * ds).sum() / total_length),
    }
    return {
        "segments": {k: v.tolist() for k, v in segments.items()},
        "total": totals,
        "envelope": envelope(P, craft, sample_m),
    }
