"""A planned polyline made flyable by a vehicle: turns of at least its radius, climbs and
descents within its flight-path angles, altitudes within its floor and ceiling.

The planner searches the map's cost over straight segments (OMPL on the voxel grid); this
turns its answer into a path of the Dubins-airplane kind, in two steps:

* horizontally, each corner becomes a circular arc of the least turn radius tangent to both
  segments (a fillet). Where two neighbouring fillets would overlap on a segment, or one
  would run past its segment's end, two corners that turn the same way become one where
  their outer segments meet (the path keeps to the outside of the bend), and otherwise the
  one nearer the join of its neighbours is dropped and they are joined, until every fillet
  fits;
* vertically, the altitudes of the corners kept, spread along the new path in proportion
  to its horizontal length, are clipped to the floor and ceiling and limited to the climb
  and descent angles by one pass forwards and one backwards (each keeps the other's bound:
  the result is the closest profile of bounded slope below and above the wanted one).

Arcs are drawn every :data:`ARC_STEP_M` (or a twentieth of the radius, if less): the
envelope (:func:`bdf.region.route.envelope`, chords of 50 m or a quarter of the radius)
then reads the radius to a fraction of a percent.

A fillet cuts its corner: its middle lies ``R (1 / cos(turn / 2) - 1)`` inside it (the
arc's *inset*), where the planner never looked. Given the tube (``in_tube``), a corner
whose arc leaves it is pushed out, along its bisector away from the turn's inside, by the
multiple of that inset (:data:`PUSH_OUT`) that leaves the fewest of the path's steps out
of the tube: at one inset the arc passes through the planned corner, which the planner
checked.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from bdf.region.route import Vehicle, as_route

ARC_STEP_M = 5.0
#: The pushes of a corner whose arc leaves the tube, in insets of its arc, tried in turn.
PUSH_OUT = (0.5, 1.0, 1.5, 2.0, 3.0)

log = logging.getLogger(__name__)


def flyable(P, craft: Vehicle, in_tube: Callable | None = None) -> np.ndarray:
    """The path (m, 3) from ``P``'s first point to its last that ``craft`` can fly.

    ``in_tube(P0, P1)``: whether each segment ``P0[k] -> P1[k]`` keeps in the tube (the
    planner's test, :meth:`planner.costmap.CostMap.segments_in_tube`); a corner whose arc
    leaves it is pushed out (module doc) as far as leaves the fewest steps out, and a
    warning says where some remain."""
    corners = _corners_that_fit(_without_repeats(as_route(P)), craft.min_turn_radius_m)
    path, at = _through(corners, craft)
    if in_tube is None:
        return path
    tried = set()
    while True:
        bad = np.flatnonzero(~in_tube(path[:-1], path[1:]))
        # the corners (not the ends) nearest the segments out of the tube, each tried once
        near = [int(np.argmin(np.abs(at[1:-1] - b))) + 1 for b in bad] if len(at) > 2 else []
        todo = [k for k in dict.fromkeys(near) if k not in tried]
        if not todo:
            break
        k = todo[0]
        tried.add(k)
        base, inset = corners, _inset(corners[:, :2], k, craft.min_turn_radius_m)
        best = len(bad)
        for fraction in PUSH_OUT if inset > 0 else ():  # the push that leaves the fewest out
            moved = _pushed_out(base, k, fraction * inset)
            if len(_corners_that_fit(moved, craft.min_turn_radius_m)) < len(moved):
                break  # pushed further, its fillet no longer fits beside its neighbours'
            candidate, where = _through(moved, craft)
            out = int((~in_tube(candidate[:-1], candidate[1:])).sum())
            if out < best:
                best, corners, path, at = out, moved, candidate, where
    if len(bad):
        log.warning(
            "the flown path leaves the tube on %d of its %d steps (near %s m): no push of its corners "
            "keeps it in",
            len(bad),
            len(path) - 1,
            np.round(path[bad[0]]).tolist(),
        )
    return path


def _through(corners: np.ndarray, craft: Vehicle) -> tuple[np.ndarray, np.ndarray]:
    """The flyable path through ``corners`` (whose fillets fit), and the index in it of each
    corner (:func:`_filleted`)."""
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
    return np.column_stack([xy, z]), at_corner


def _inset(xy: np.ndarray, k: int, radius: float) -> float:
    """How far inside corner ``k`` of ``xy`` the middle of its fillet lies (at most the radius)."""
    turn = abs(_turns(xy[k - 1 : k + 2])[0])
    return radius * min(1.0 / np.cos(turn / 2) - 1.0, 1.0)


def _pushed_out(corners: np.ndarray, k: int, distance: float) -> np.ndarray:
    """``corners`` with corner ``k`` moved ``distance`` along its bisector, away from the
    inside of its turn (its altitude kept)."""
    u, w = (corners[k, :2] - corners[k - 1, :2]), (corners[k + 1, :2] - corners[k, :2])
    inward = w / np.linalg.norm(w) - u / np.linalg.norm(u)
    moved = corners.copy()
    moved[k, :2] -= distance * inward / np.linalg.norm(inward)
    return moved


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


def _corners_that_fit(P: np.ndarray, radius: float) -> np.ndarray:
    """The corners of ``P`` (its ends kept) whose fillets of ``radius`` fit on their segments
    beside their neighbours'. Where two do not fit on the segment between them: if they
    turn the same way they become one corner where their outer segments meet (the path
    keeps to the outside of the bend), else the one whose neighbours' join passes nearer to
    it is dropped (the path moves least from where the planner looked)."""
    P = P.copy()
    while len(P) > 2:
        xy = P[:, :2]
        turns = _turns(xy)
        tangent = np.concatenate([[0.0], radius * np.tan(np.abs(turns) / 2), [0.0]])
        length = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        excess = tangent[:-1] + tangent[1:] - length
        worst = int(np.argmax(excess))
        if excess[worst] <= 1e-9 * max(length[worst], 1.0):
            break
        a, b = worst, worst + 1  # the corners beside the segment too short (one may be an end)
        meet = None
        if 0 < a and b < len(P) - 1 and turns[a - 1] * turns[b - 1] > 0:
            meet = _meeting(xy[a - 1], xy[a], xy[b], xy[b + 1])
        if meet is None:
            interior = [c for c in (a, b) if 0 < c < len(P) - 1]
            P = np.delete(P, min(interior, key=lambda c: _off(xy[c], xy[c - 1], xy[c + 1])), axis=0)
        else:
            P = np.vstack([P[:a], [[*meet, 0.5 * (P[a, 2] + P[b, 2])]], P[b + 1 :]])
    return P


def _off(p, a, b) -> float:
    """The distance from ``p`` to the segment ``a -> b``."""
    d = b - a
    t = np.clip(np.dot(p - a, d) / max(np.dot(d, d), 1e-300), 0.0, 1.0)
    return float(np.linalg.norm(p - a - t * d))


def _meeting(p0, p1, q0, q1) -> np.ndarray | None:
    """Where the line ``p0 -> p1`` carried on meets the line ``q1 -> q0`` carried back: the
    corner of the two lines, if it lies ahead of ``p0`` and before ``q1``."""
    u, w = p1 - p0, q1 - q0
    cross = u[0] * w[1] - u[1] * w[0]
    if abs(cross) < 1e-12 * np.linalg.norm(u) * np.linalg.norm(w):
        return None
    d = q0 - p0
    t = (d[0] * w[1] - d[1] * w[0]) / cross  # along u from p0
    r = (d[0] * u[1] - d[1] * u[0]) / cross  # along w from q0
    if t <= 1.0 or r >= 0.0:
        return None
    return p0 + t * u


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
