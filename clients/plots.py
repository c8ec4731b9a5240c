"""Pictures of a served map, like the paper's figures, from grids fetched with the SDK.

* :func:`plot_slice`: mean and std of one component on a horizontal slice (paper fig. 4);
* :func:`plot_arrows`: horizontal flow arrows over the std map;
* :func:`plot_modes`: each traffic class's arrows (a directional map), as the viewer's
  ``modes`` layer draws them;
* :func:`plot_tube`: the tube's voxels in 3D, coloured by vertical velocity (paper fig. 7).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from clients.sdk import Grid, Tubes

COMPONENTS = {"e": 0, "n": 1, "u": 2}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    _pyplot().close(fig)
    return path


def _level(grid: Grid, alt_m: float) -> int:
    return int(np.argmin(np.abs(grid.z - alt_m)))


def plot_slice(grid: Grid, alt_m: float, component: str, path, title: str = "") -> Path:
    """Mean and std of ``component`` (e, n, u) at the grid level nearest ``alt_m``; the mean
    is grey where no tile has data (only the prior's 0 is there), as in the viewer."""
    plt = _pyplot()
    c, k = COMPONENTS[component], _level(grid, alt_m)
    extent = [grid.x[0] / 1e3, grid.x[-1] / 1e3, grid.y[0] / 1e3, grid.y[-1] / 1e3]
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.4), constrained_layout=True)
    mean = np.ma.masked_array(grid.mean[:, :, k, c].T, ~grid.known[:, :, k].T)
    std = grid.std[:, :, k, c].T
    limit = float(np.abs(mean).max()) if mean.count() else 1.0
    for ax, values, cmap, label, kw in (
        (axes[0], mean, "RdBu_r", f"mean v{component} [m/s]", {"vmin": -limit, "vmax": limit}),
        (axes[1], std, "magma_r", f"predictive std of v{component} [m/s]", {}),
    ):
        cmap = plt.get_cmap(cmap).with_extremes(bad="0.8")
        im = ax.imshow(values, origin="lower", extent=extent, cmap=cmap, aspect="equal", **kw)
        fig.colorbar(im, ax=ax, label=label)
        ax.set(xlabel="east [km]", ylabel="north [km]")
    axes[0].set_title(f"{title} mean v{component} at {grid.z[k]:.0f} m")
    axes[1].set_title(f"{title} uncertainty at {grid.z[k]:.0f} m")
    return _save(fig, path)


def plot_arrows(grid: Grid, alt_m: float, path, title: str = "") -> Path:
    """Horizontal mean flow (arrows) over the horizontal predictive std at one level."""
    plt = _pyplot()
    k = _level(grid, alt_m)
    std = np.hypot(grid.std[:, :, k, 0], grid.std[:, :, k, 1]).T
    fig, ax = plt.subplots(figsize=(8, 6.5), constrained_layout=True)
    extent = [grid.x[0] / 1e3, grid.x[-1] / 1e3, grid.y[0] / 1e3, grid.y[-1] / 1e3]
    im = ax.imshow(std, origin="lower", extent=extent, cmap="magma_r", aspect="equal")
    fig.colorbar(im, ax=ax, label="predictive std of horizontal velocity [m/s]")
    stride = max(len(grid.x) // 25, 1)
    sl = (slice(None, None, stride), slice(None, None, stride), k)
    gx, gy = np.meshgrid(grid.x[::stride] / 1e3, grid.y[::stride] / 1e3, indexing="ij")
    ax.quiver(gx, gy, grid.mean[sl][..., 0], grid.mean[sl][..., 1], color="cyan", width=0.003)
    ax.set(xlabel="east [km]", ylabel="north [km]", title=f"{title} mean flow at {grid.z[k]:.0f} m")
    return _save(fig, path)


def plot_modes(grid: Grid, alt_m: float, path, title: str = "", min_share: float = 0.05) -> Path:
    """Each traffic class with at least ``min_share`` of the traffic as an arrow along its
    mode's horizontal mean, coloured by heading, wider with its share, over the mixture's
    speed (a grid fetched with ``modes=True``)."""
    from service.slices import render_slice

    if grid.share is None:
        raise ValueError("plot_modes needs a grid fetched with modes=True")
    k = _level(grid, alt_m)
    png = render_slice(
        grid.x,
        grid.y,
        grid.mean[:, :, k],
        grid.std[:, :, k],
        grid.known[:, :, k],
        alt_m=float(grid.z[k]),
        layer="modes",
        component="e",
        max_std_mps=1.0,
        title=title,
        share=grid.share[:, :, k],
        share_std=grid.share_std[:, :, k],
        mode_mean=grid.mode_mean[:, :, k],
        mode_known=~grid.mode_prior_only[:, :, k],
        min_share=min_share,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)
    return path


def plot_tube(tubes: Tubes, max_std_mps: float, path, title: str = "", max_points: int = 20_000) -> Path:
    """The tube's voxels in 3D, coloured by their mean vertical velocity."""
    plt = _pyplot()
    P, vu = tubes.points, tubes.mean[:, 2]
    if len(P) > max_points:  # a picture does not need every voxel
        keep = np.random.default_rng(0).choice(len(P), max_points, replace=False)
        P, vu = P[keep], vu[keep]
    fig = plt.figure(figsize=(9, 7), constrained_layout=True)
    ax = fig.add_subplot(projection="3d")
    limit = float(np.abs(vu).max()) if len(vu) else 1.0
    sc = ax.scatter(
        P[:, 0] / 1e3, P[:, 1] / 1e3, P[:, 2], c=vu, cmap="coolwarm", s=2, vmin=-limit, vmax=limit
    )
    fig.colorbar(sc, ax=ax, shrink=0.6, label="mean vertical velocity [m/s]")
    ax.set(
        xlabel="east [km]",
        ylabel="north [km]",
        zlabel="up [m]",
        title=f"{title} tube: std < {max_std_mps:g} m/s ({len(tubes.points)} voxels)",
    )
    return _save(fig, path)
