"""The route picture: top view over the tube at the route's mean altitude, and the profile."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from planner.routes import RoutePlan


def plot_route(plan: RoutePlan, path) -> Path:
    """Write a PNG: left, the largest predictive std at the route's mean altitude with the
    tube's edge, the mean flow and both routes (flown; dotted, as planned before they were
    made flyable); right, altitude along each route."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    cm, bound = plan.costmap, plan.costmap.weights.max_std_mps
    main = plan.route or plan.baseline
    k = int(np.argmin(np.abs(cm.axes[2] - main.enu[:, 2].mean())))
    # the view: the routes and a margin of a fifth of their extent (not the whole region)
    routes = [r for r in (plan.route, plan.baseline) if r is not None]
    xy = np.vstack([r.enu[:, :2] for r in routes])
    side_m = 1.4 * max(np.ptp(xy[:, 0]), np.ptp(xy[:, 1]), 4000.0)  # a square view, a margin round them
    centre = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    lo, hi = centre - side_m / 2, centre + side_m / 2
    ix = np.flatnonzero((cm.axes[0] >= lo[0]) & (cm.axes[0] <= hi[0]))
    iy = np.flatnonzero((cm.axes[1] >= lo[1]) & (cm.axes[1] <= hi[1]))
    x, y = cm.axes[0][ix] / 1e3, cm.axes[1][iy] / 1e3
    s = cm.table[:, 0].reshape(cm.shape)[np.ix_(ix, iy, [k])][:, :, 0].T
    mean = cm.table[:, 3:6].reshape(*cm.shape, 3)[np.ix_(ix, iy, [k])][:, :, 0]
    aspect = float(np.ptp(x) / max(np.ptp(y), 1e-9))  # the planning grid's, where it clips the view
    fig, (top, side) = plt.subplots(
        1, 2, figsize=(6.6 * aspect + 6.5, 7.2), width_ratios=[max(aspect, 0.3), 0.9], constrained_layout=True
    )
    # green inside the tube, red outside, the bound where they meet
    norm = TwoSlopeNorm(vmin=min(float(s.min()), 0.5 * bound), vcenter=bound, vmax=2.0 * bound)
    im = top.pcolormesh(x, y, s, cmap="RdYlGn_r", norm=norm, shading="nearest")
    fig.colorbar(
        im, ax=top, label="largest predictive std [m/s] (green: inside the tube)", extend="max", shrink=0.8
    )
    top.contour(x, y, s, levels=[bound], colors="black", linewidths=1.0)
    stride = max(len(x) // 14, 1)
    q = top.quiver(
        x[::stride],
        y[::stride],
        mean[::stride, ::stride, 0].T,
        mean[::stride, ::stride, 1].T,
        color="0.15",
        width=0.0035,
    )
    top.quiverkey(
        q,
        0.5,
        -0.1,
        100.0,
        "mean flow: 100 m/s",
        labelpos="E",
        coordinates="axes",
        fontproperties={"size": 8},
    )
    styles = {"risk-aware": ("tab:blue", "-"), "shortest": ("tab:purple", "--")}
    for r in routes:
        color, ls = styles[r.name]
        label = (
            f"{r.name}: {r.metrics['length_m'] / 1e3:.1f} km, integrated risk "
            f"{r.metrics['integrated_risk_m'] / 1e3:.1f} km at the bound"
        )
        top.plot(r.enu[:, 0] / 1e3, r.enu[:, 1] / 1e3, ls, color=color, lw=2.2, label=label)
        dist = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(r.enu, axis=0), axis=1))]) / 1e3
        side.plot(dist, r.enu[:, 2], ls, color=color, lw=2, label=f"{r.name}, flown")
        if r.envelope is not None:  # the planner's polyline before it was made flyable
            top.plot(r.planned[:, 0] / 1e3, r.planned[:, 1] / 1e3, ":", color=color, lw=1, alpha=0.8)
            flat = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(r.planned, axis=0), axis=1))]) / 1e3
            side.plot(flat, r.planned[:, 2], ":", color=color, lw=1, alpha=0.8, label=f"{r.name}, planned")
    top.plot(*main.enu[0, :2] / 1e3, "o", color="white", mec="black", ms=9, label="start")
    top.plot(*main.enu[-1, :2] / 1e3, "*", color="white", mec="black", ms=13, label="goal")
    top.plot([], [], color="black", lw=1, label=f"tube edge: std = {bound:.1f} m/s")
    top.set(
        xlabel="east [km]",
        ylabel="north [km]",
        aspect="equal",
        xlim=(x[0], x[-1]),
        ylim=(y[0], y[-1]),
        title=f"{plan.region.name}: the tube at {cm.axes[2][k]:.0f} m\n(the route's mean altitude)",
    )
    alts = np.concatenate(
        [r.enu[:, 2] for r in routes] + [r.planned[:, 2] for r in routes if r.envelope is not None]
    )
    middle, half = 0.5 * (alts.min() + alts.max()), max(0.5 * np.ptp(alts) * 1.15, 150.0)
    side.set(
        xlabel="distance along the route [km]",
        ylabel="altitude [m, region ENU up]",
        title="altitude profile",
        ylim=(middle - half, middle + half),  # a level flight looks level: at least 300 m shown
    )
    side.add_artist(side.legend(fontsize=8, loc="upper left"))  # the profile's lines; the map's below
    side.legend(
        *top.get_legend_handles_labels(),
        loc="upper center",
        bbox_to_anchor=(0.5, -0.11),
        fontsize=8,
        frameon=False,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
