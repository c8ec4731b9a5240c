"""A planned polyline made flyable by a vehicle: turns of at least its radius, climbs and
descents within its flight-path angles, altitudes within its floor and ceiling.

The planner searches the map's cost over straight segments (OMPL on the voxel grid); this
turns its answer into a path of the Dubins-airplane kind, in two steps:

* horizontally, each corner becomes a circular arc of the least turn radius tangent to both
  segments (a fillet). Where two neighbouring fillets would overlap on a segment, or one
  would run past its segment's end, the corner that needs the longer tangent is dropped and
  its neighbours are joined, until every fillet fits;
* vertically, the altitudes of the corners kept, spread along the new path in proportion
  to its horizontal length, are clipped to the floor and ceiling and limited to the climb
  and descent angles by one pass forwards and one backwards (each keeps the other's bound:
  the result is the closest profile of bounded slope below and above the wanted one).

Arcs are drawn every :data:`ARC_STEP_M` (or a twentieth of the radius, if less): the
envelope (:func:`bdf.region.route.envelope`, chords of 50 m or a quarter of the radius)
then reads the radius to a fraction of a percent.
"""

from __future__ import annotations

import numpy as np

from bdf.region.route import Vehicle, as_route

ARC_STEP_M = 5.0


def flyable(P, craft: Vehicle) -> np.ndarray:
    """The path (m, 3) from ``P``'s first point to its last that ``craft`` can fly."""
    P = _without_repeats(as_route(P))
    keep = _corners_that_fit(P[:, :2], craft.min_turn_radius_m)
    corners = P[keep]
    arc_step_m = min(ARC_STEP_M, craft.min_turn_radius_m / 20)
    xy, at_corner = _filleted(corners[:, :2], craft.min_turn_radius_m, arc_step_m)
    h = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    wanted = np.interp(h, h[at_corner], corners[:, 2])
    z = _bounded_slope(
        np.clip(wanted, craft.floor_m, craft.ceiling_m),
        np.diff(h),
        np.tan(np.radians(craft.max_climb_deg)),
        np.tan(np.radians(craft.max_descent_deg)),
    )
    return np.column_stack([xy, z])


def _without_repeats(P: np.ndarray) -> np.ndarray:
    """``P`` without the points horizontally within a millimetre of the one before (a
    vertical step: the slope limit spreads it), its last point kept exactly."""
    kept = [P[0]]
    for p in P[1:]:
        if np.hypot(*(p[:2] - kept[-1][:2])) >= 1e-3:
            kept.append(p)
    if len(kept) == 1:
        raise ValueError("a route to fly needs its ends apart horizontally")
    kept[-1] = P[-1]
    return np.array(kept)


def _turns(xy: np.ndarray) -> np.ndarray:
    """The signed turn (radians, left positive) at each interior point of ``xy``."""
    d = np.diff(xy, axis=0)
    u, w = d[:-1], d[1:]
    return np.arctan2(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0], (u * w).sum(axis=1))


def _corners_that_fit(xy: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the points kept: the ends, and the corners whose fillets of ``radius``
    fit on their segments beside their neighbours'."""
    keep = list(range(len(xy)))
    while len(keep) > 2:
        sub = xy[keep]
        tangent = np.concatenate([[0.0], radius * np.tan(np.abs(_turns(sub)) / 2), [0.0]])
        length = np.linalg.norm(np.diff(sub, axis=0), axis=1)
        excess = tangent[:-1] + tangent[1:] - length
        worst = int(np.argmax(excess))
        if excess[worst] <= 1e-9 * max(length[worst], 1.0):
            break
        drop = worst if tangent[worst] >= tangent[worst + 1] else worst + 1  # the ends have none
        del keep[drop]
    return np.array(keep)


def _filleted(xy: np.ndarray, radius: float, arc_step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The horizontal path through ``xy`` with each corner a fillet of ``radius`` (drawn
    every ``arc_step_m``), and the index in it of each point of ``xy`` (a corner's: the
    middle of its arc)."""
    out, at = [xy[:1]], [0]
    turns = _turns(xy)
    for i, turn in enumerate(turns, start=1):
        u = (xy[i] - xy[i - 1]) / np.linalg.norm(xy[i] - xy[i - 1])
        w = (xy[i + 1] - xy[i]) / np.linalg.norm(xy[i + 1] - xy[i])
        if abs(turn) < 1e-9:
            at.append(sum(len(p) for p in out))
            out.append(xy[i : i + 1])
            continue
        t = radius * np.tan(abs(turn) / 2)
        start = xy[i] - t * u
        left = np.array([-u[1], u[0]]) * np.sign(turn)
        centre = start + radius * left
        a0 = np.arctan2(*(start - centre)[::-1])
        n = max(int(np.ceil(radius * abs(turn) / arc_step_m)), 2)
        angles = a0 + np.linspace(0.0, turn, n + 1)
        arc = centre + radius * np.column_stack([np.cos(angles), np.sin(angles)])
        arc[-1] = xy[i] + t * w  # the tangent point on the next segment, exactly
        at.append(sum(len(p) for p in out) + n // 2)
        out.append(arc)
    at.append(sum(len(p) for p in out))
    out.append(xy[-1:])
    path = np.vstack(out)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(path, axis=0), axis=1) > 1e-9])
    index = np.cumsum(keep) - 1
    return path[keep], index[np.array(at)]


def _bounded_slope(z: np.ndarray, dh: np.ndarray, climb: float, descent: float) -> np.ndarray:
    """``z`` with each step's rise at most ``climb * dh`` and fall at most ``descent * dh``:
    backwards from the end (every altitude within reach of the goal's), then forwards from
    the start, which ends at the goal's altitude wherever the route is long enough to get
    there."""
    z, start = z.copy(), z[0]
    for i in range(len(z) - 2, -1, -1):
        z[i] = min(max(z[i], z[i + 1] - climb * dh[i]), z[i + 1] + descent * dh[i])
    z[0] = start  # where the vehicle is
    for i in range(1, len(z)):
        z[i] = min(max(z[i], z[i - 1] - descent * dh[i - 1]), z[i - 1] + climb * dh[i - 1])
    return z
