"""The reference optimum: Dijkstra on the cost map's voxel lattice (26-connected).

It minimises the same cost as the OMPL objective over paths restricted to lattice edges, so
it tells how close a sampling planner gets; being restricted to 26 directions, it can be a
few per cent above the continuous optimum.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from planner.search import PlanningProblem


def lattice_optimum(problem: PlanningProblem) -> tuple[float, np.ndarray]:
    """(cost, waypoints) of the cheapest lattice path from the node nearest the start to the
    node nearest the goal, plus the exact start and goal legs; ``inf`` if none is valid."""
    cm = problem.costmap
    lower, upper = problem.bounds()
    inside = [(a >= lower[d] - 1e-9) & (a <= upper[d] + 1e-9) for d, a in enumerate(cm.axes)]
    axes = [a[m] for a, m in zip(cm.axes, inside, strict=True)]
    shape = tuple(len(a) for a in axes)
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    index = np.arange(len(nodes)).reshape(shape)
    sources, targets = [], []
    for offset in itertools.product((-1, 0, 1), repeat=3):
        if offset <= (0, 0, 0):  # each undirected edge once
            continue
        src = index[tuple(slice(max(-o, 0), n - max(o, 0)) for o, n in zip(offset, shape, strict=True))]
        dst = index[tuple(slice(max(o, 0), n - max(-o, 0)) for o, n in zip(offset, shape, strict=True))]
        sources.append(src.ravel())
        targets.append(dst.ravel())
    src, dst = np.concatenate(sources), np.concatenate(targets)
    valid = problem.segments_valid(nodes[src], nodes[dst])
    src, dst = src[valid], dst[valid]
    a, b = nodes[src], nodes[dst]
    if problem.objective == "length":
        forward = backward = np.linalg.norm(b - a, axis=1)
    else:  # the flow term depends on the direction of flight
        forward, backward = problem.costmap.segment_costs(a, b), problem.costmap.segment_costs(b, a)
    weight = np.concatenate([forward, backward])
    src, dst = np.concatenate([src, dst]), np.concatenate([dst, src])
    graph = coo_matrix((weight, (src, dst)), shape=(len(nodes), len(nodes))).tocsr()
    start, goal = np.asarray(problem.start), np.asarray(problem.goal)
    s = int(np.argmin(np.linalg.norm(nodes - start, axis=1)))
    g = int(np.argmin(np.linalg.norm(nodes - goal, axis=1)))
    dist, pred = dijkstra(graph, indices=s, return_predecessors=True)
    if not np.isfinite(dist[g]):
        return np.inf, np.empty((0, 3))
    chain = [g]
    while chain[-1] != s:
        chain.append(pred[chain[-1]])
    P = np.vstack([start, nodes[chain[::-1]], goal])
    return problem.path_cost(P), P
