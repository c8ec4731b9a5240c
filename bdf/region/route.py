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

from collections.abc import Callable
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
#: The envelope's finest sample spacing (m): a vehicle turning tighter than a chord of three
#: of them is judged as one turning within it (its own radius is not resolved).
MIN_ENVELOPE_SAMPLE_M = 1.0
#: The least tube bound (m/s): the risk divides by it.
MIN_TUBE_STD_MPS = 1e-3
#: The fastest a route may be flown, or a vehicle cruise (m/s; about Mach 3).
MAX_ROUTE_SPEED_MPS = 1000.0
#: Route samples read and judged at once: a route's memory is a chunk's, not its length's.
CHUNK_SAMPLES = 4096
#: A route's cost in query points counts this many envelope samples as one: an envelope
#: sample costs 10 to 29 times less than a sample read on the map (0.13 us against 1.34 us
#: with one class, 3.77 us with 8 sectors: bench/RESULTS.md, "Route assessment"), and the
#: margin covers a machine's noise.
ENVELOPE_SAMPLES_PER_POINT = 4


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
        if self.cruise_mps > MAX_ROUTE_SPEED_MPS:
            raise ValueError(f"cruise_mps must be at most {MAX_ROUTE_SPEED_MPS:g}, got {self.cruise_mps!r}")
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
    path = _Path(P)
    return path.at(np.arange(path.samples(spacing_m)) * spacing_m)


class _Path:
    """A polyline by its 3-D arc length: points at any lengths along it (its end beyond)."""

    def __init__(self, P: np.ndarray):
        self.P = P
        self.s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
        self.length = float(self.s[-1])

    def samples(self, spacing_m: float) -> int:
        """How many points every ``spacing_m`` from its start, its end included."""
        return int(np.ceil(self.length / spacing_m)) + 1

    def at(self, s: np.ndarray) -> np.ndarray:
        s = np.minimum(s, self.length)
        return np.stack([np.interp(s, self.s, self.P[:, d]) for d in range(3)], axis=1)


def _radii(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The radius of the horizontal circle through ``a``, ``b``, ``c`` (rows; inf: a line)."""
    ab, bc, ca = (np.linalg.norm(u[:, :2] - v[:, :2], axis=1) for u, v in ((a, b), (b, c), (c, a)))
    cross = np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    with np.errstate(divide="ignore"):
        return np.where(cross > 1e-9 * ab * bc, ab * bc * ca / (2.0 * cross), np.inf)


def turn_radii(P: np.ndarray, sample_m: float = SAMPLE_M, window_m: float = TURN_WINDOW_M) -> np.ndarray:
    """The horizontal turn radius (m) at each sample every ``sample_m`` along ``P``: the
    circle through the samples ``window_m`` before and after it (inf on a straight line)."""
    Q = resample(P, sample_m)
    k = max(round(window_m / sample_m), 1)
    if len(Q) < 2 * k + 1:
        return np.full(0, np.inf)
    return _radii(Q[: -2 * k], Q[k:-k], Q[2 * k :])


def envelope_sampling(craft: Vehicle, sample_m: float = SAMPLE_M) -> tuple[float, float]:
    """The envelope's sample spacing and turn window (m) for ``craft``: turns are read over
    chords of at most a quarter of its turn radius (within the arc of a 30-degree turn),
    sampled three times as often, and never finer than :data:`MIN_ENVELOPE_SAMPLE_M`."""
    window = max(min(TURN_WINDOW_M, craft.min_turn_radius_m / 4), 3 * MIN_ENVELOPE_SAMPLE_M)
    return min(sample_m, window / 3), window


def envelope(
    P,
    craft: Vehicle,
    sample_m: float = SAMPLE_M,
    tolerance: float = ENVELOPE_TOLERANCE,
    checkpoint: Callable[[], None] | None = None,
) -> dict:
    """Whether ``craft`` can fly the polyline ``P`` as it is: the least turn radius (None
    where it never turns), the steepest climb and descent (per sample of it), the lowest
    and highest altitude, and for each limit whether it holds (within ``tolerance``).
    Sampled as :func:`envelope_sampling` says, :data:`CHUNK_SAMPLES` at a time
    (``checkpoint()`` between chunks): its memory does not grow with the route's length."""
    path = _Path(as_route(P))
    step, window = envelope_sampling(craft, sample_m)
    n, k = path.samples(step), max(round(window / step), 1)
    radius, climb, descent = np.inf, 0.0, 0.0
    low, high = np.inf, -np.inf
    for lo in range(0, n, CHUNK_SAMPLES):
        if checkpoint is not None:
            checkpoint()
        i = np.arange(lo, min(lo + CHUNK_SAMPLES, n))
        first = max(lo - k, 0)  # the chunk's samples and a turn window on either side, once
        Q = path.at(np.arange(first, min(lo + CHUNK_SAMPLES + k, n)) * step)
        own = Q[i - first]
        low, high = min(low, float(own[:, 2].min())), max(high, float(own[:, 2].max()))
        nxt = i[i + 1 < n]  # each step to the next sample
        if len(nxt):
            delta = Q[nxt + 1 - first] - Q[nxt - first]
            angle = np.degrees(np.arctan2(delta[:, 2], np.hypot(delta[:, 0], delta[:, 1])))
            climb, descent = max(climb, float(angle.max())), max(descent, float(-angle.min()))
        mid = i[(i >= k) & (i + k < n)]  # each sample with a full window on both sides
        if len(mid):
            radii = _radii(Q[mid - k - first], Q[mid - first], Q[mid + k - first])
            radius = min(radius, float(radii.min()))
    out = {
        "min_turn_radius_m": radius if np.isfinite(radius) else None,  # None: it never turns
        "max_climb_deg": climb,
        "max_descent_deg": descent,
        "min_alt_m": low,
        "max_alt_m": high,
    }
    slack = 1.0 + tolerance
    checks = {
        "turn_ok": bool(radius * slack >= craft.min_turn_radius_m),
        "climb_ok": bool(climb <= craft.max_climb_deg * slack),
        "descent_ok": bool(descent <= craft.max_descent_deg * slack),
        "altitude_ok": bool(low >= craft.floor_m - 1.0 and high <= craft.ceiling_m + 1.0),
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
    with np.errstate(over="ignore"):
        duration = np.diff(times)
    if times.shape != (len(P),) or not np.all(np.isfinite(duration)) or np.any(duration <= 0):
        raise ValueError(f"times_s must be {len(P)} finite, increasing seconds, one per point")
    delta = np.diff(P, axis=0)
    with np.errstate(over="ignore"):
        speed = np.linalg.norm(delta, axis=1) / duration
    fast = np.flatnonzero(~(speed <= MAX_ROUTE_SPEED_MPS))
    if len(fast):
        raise ValueError(
            f"times_s: segment {int(fast[0])} is flown at {speed[fast[0]]:.4g} m/s, faster than "
            f"{MAX_ROUTE_SPEED_MPS:g} m/s"
        )
    if heading_deg is None:
        return P, times, np.degrees(np.arctan2(delta[:, 0], delta[:, 1])) % 360.0
    heading = np.asarray(heading_deg, float).ravel()
    if heading.shape != (len(P) - 1,) or not np.all(np.isfinite(heading)):
        raise ValueError(f"heading_deg must be {len(P) - 1} finite degrees, one per segment")
    return P, times, heading


def samples(P: np.ndarray, craft: Vehicle, sample_m: float = SAMPLE_M) -> tuple[int, int]:
    """What :func:`assess` of route ``P`` costs, known before any work: the samples it reads
    on the map (one per ``sample_m`` piece of each segment) and the samples of its envelope
    (:func:`envelope_sampling`)."""
    length = np.linalg.norm(np.diff(P, axis=0), axis=1)
    on_map = int(np.maximum(np.ceil(length / sample_m), 1).sum())
    return on_map, _Path(P).samples(envelope_sampling(craft, sample_m)[0])


def assess(
    region_map: RegionMap,
    P,
    *,
    max_std_mps: float,
    craft: Vehicle,
    times_s=None,
    heading_deg=None,
    sample_m: float = SAMPLE_M,
    checkpoint: Callable[[], None] | None = None,
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

    The map is read :data:`CHUNK_SAMPLES` samples at a time (``checkpoint()`` between
    chunks), so memory stays bounded whatever the route's length (:func:`samples`).
    """
    spec = region_map.spec
    P, times_s, heading = checked(P, craft, times_s, heading_deg)
    outside = np.flatnonzero(~spec.inside(P))
    if len(outside):
        raise ValueError(f"route points {outside[:5].tolist()} are outside region {spec.name!r}")
    if not (np.isfinite(max_std_mps) and MIN_TUBE_STD_MPS <= max_std_mps):
        raise ValueError(f"max_std_mps must be at least {MIN_TUBE_STD_MPS:g} m/s, got {max_std_mps!r}")
    n_seg = len(P) - 1
    delta = np.diff(P, axis=0)
    length = np.linalg.norm(delta, axis=1)
    velocity = delta / np.diff(times_s)[:, None]
    pieces = np.maximum(np.ceil(length / sample_m).astype(np.int64), 1)
    ends = np.cumsum(pieces)
    sums = {key: np.zeros(n_seg) for key in _WEIGHED}
    worst = np.full(n_seg, -np.inf)
    for lo in range(0, int(ends[-1]), CHUNK_SAMPLES):
        if checkpoint is not None:
            checkpoint()
        index = np.arange(lo, min(lo + CHUNK_SAMPLES, int(ends[-1])))
        seg = np.searchsorted(ends, index, side="right")
        within = (index - (ends[seg] - pieces[seg]) + 0.5) / pieces[seg]
        values = _read(region_map, P[seg] + within[:, None] * delta[seg], velocity[seg], heading[seg])
        values["in_tube_fraction"] = (values["std"] <= max_std_mps).astype(float)
        values["integrated_risk_m"] = values["std"] / max_std_mps
        ds = length[seg] / pieces[seg]
        for key, name in _WEIGHED.items():
            sums[key] += np.bincount(seg, weights=values[name] * ds, minlength=n_seg)
        np.maximum.at(worst, seg, values["std"])
    segments = {"length_m": length, "duration_s": np.diff(times_s), "max_std_mps": worst}
    total_length = float(length.sum())
    totals = {
        "length_m": total_length,
        "duration_s": float(times_s[-1] - times_s[0]),
        "max_std_mps": float(worst.max()),
    }
    for key in _WEIGHED:
        integral = key == "integrated_risk_m"  # a sum along the route; the rest are means
        segments[key] = sums[key] if integral else sums[key] / length
        totals[key] = float(sums[key].sum() if integral else sums[key].sum() / total_length)
    return {
        "segments": {k: v.tolist() for k, v in segments.items()},
        "total": totals,
        "envelope": envelope(P, craft, sample_m, checkpoint=checkpoint),
    }


#: the metrics weighed by length along the route, and the sample values they weigh
_WEIGHED = {
    "mean_std_mps": "std",
    "in_tube_fraction": "in_tube_fraction",
    "integrated_risk_m": "integrated_risk_m",
    "conflict_exposure": "crossing",
    "flow_mismatch_mps": "mismatch",
    "flow_heading_offset_deg": "offset",
    "traffic_speed_mps": "traffic_speed",
}


def _read(region_map: RegionMap, X: np.ndarray, velocity: np.ndarray, heading: np.ndarray) -> dict:
    """The map at route samples ``X`` flown at ``velocity`` on ``heading``: the std of the
    mode flown (the heading's, :meth:`bdf.posterior.Modes.answer`; the slow class's below its
    speed), the share of crossing traffic, and the mode's mean against the route's."""
    sectors = region_map.spec.sectors
    modes = region_map.predict_modes(X)
    traffic, std = modes.answer(sectors, heading)
    crossing = np.zeros(len(X))
    if sectors.classes > 1:
        slow = np.hypot(velocity[:, 0], velocity[:, 1]) < sectors.slow_mps
        traffic[slow], std[slow] = modes.mean[slow, -1], modes.std[slow, -1]
        off = np.abs((sectors.centres_deg[None, :] - heading[:, None] + 180.0) % 360.0 - 180.0)
        crossing = (modes.share[:, : sectors.directions] * (off >= CROSSING_DEG)).sum(axis=1)
    traffic_heading = np.degrees(np.arctan2(traffic[:, 0], traffic[:, 1]))
    return {
        "std": std.max(axis=1),
        "crossing": crossing,
        "mismatch": np.linalg.norm(velocity - traffic, axis=1),
        "offset": np.abs((traffic_heading - heading + 180.0) % 360.0 - 180.0),
        "traffic_speed": np.hypot(traffic[:, 0], traffic[:, 1]),
    }
