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

    cm, bound = plan.costmap, plan.costmap.weights.max_std_mps
    main = plan.route or plan.baseline
    k = int(np.argmin(np.abs(cm.axes[2] - main.enu[:, 2].mean())))
    x, y = cm.axes[0] / 1e3, cm.axes[1] / 1e3
    s = cm.table[:, 0].reshape(cm.shape)[:, :, k].T
    mean = cm.table[:, 3:6].reshape(*cm.shape, 3)[:, :, k]
    fig, (top, side) = plt.subplots(1, 2, figsize=(13, 5.4), width_ratios=[1.2, 1], constrained_layout=True)
    im = top.pcolormesh(x, y, s, cmap="magma_r", shading="nearest", vmax=max(3 * bound, np.percentile(s, 5)))
    fig.colorbar(im, ax=top, label="largest predictive std [m/s]")
    top.contour(x, y, s, levels=[bound], colors="cyan", linewidths=1.2)
    stride = max(len(x) // 18, 1)
    top.quiver(
        x[::stride],
        y[::stride],
        mean[::stride, ::stride, 0].T,
        mean[::stride, ::stride, 1].T,
        color="white",
        alpha=0.7,
        width=0.003,
    )
    styles = {"risk-aware": ("tab:green", "-"), "shortest": ("tab:red", "--")}
    for r in (plan.route, plan.baseline):
        if r is None:
            continue
        color, ls = styles[r.name]
        label = f"{r.name}: {r.metrics['length_m'] / 1e3:.2f} km, risk {r.metrics['integrated_risk_m']:.0f}"
        top.plot(r.enu[:, 0] / 1e3, r.enu[:, 1] / 1e3, ls, color=color, lw=2, label=label)
        dist = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(r.enu, axis=0), axis=1))]) / 1e3
        side.plot(dist, r.enu[:, 2], ls, color=color, lw=2, label=f"{r.name}, flown")
        if r.envelope is not None:  # the planner's polyline before it was made flyable
            top.plot(r.planned[:, 0] / 1e3, r.planned[:, 1] / 1e3, ":", color=color, lw=1, alpha=0.8)
            flat = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(r.planned, axis=0), axis=1))]) / 1e3
            side.plot(flat, r.planned[:, 2], ":", color=color, lw=1, alpha=0.8, label=f"{r.name}, planned")
    top.plot(*main.enu[0, :2] / 1e3, "o", color="white", mec="black", ms=8)
    top.plot(*main.enu[-1, :2] / 1e3, "*", color="white", mec="black", ms=12)
    top.plot([], [], color="cyan", label=f"tube edge: std = {bound:g} m/s")
    top.legend(loc="upper left", fontsize=8)
    top.set(
        xlabel="east [km]",
        ylabel="north [km]",
        aspect="equal",
        title=f"{plan.region.name}: tube at {cm.axes[2][k]:.0f} m (mean altitude of the route)",
    )
    side.set(
        xlabel="distance along the route [km]", ylabel="altitude [m, region ENU up]", title="altitude profile"
    )
    side.legend()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
