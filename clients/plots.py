"""Pictures of a served map, like the paper's figures, from grids fetched with the SDK.

* :func:`plot_slice`: mean and std of one component on a horizontal slice (paper fig. 4);
* :func:`plot_arrows`: horizontal flow arrows over the std map;
* :func:`plot_modes`: each traffic class's arrows (a directional map), as the viewer's
  ``modes`` layer draws them;
* :func:`plot_tube`: the tube as maps at a few altitudes, coloured by vertical velocity (the
  paper's fig. 7 drew it in 3D, whose depth a page cannot show).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from clients.sdk import Grid, Tubes
from service.slices import MODE_COLOUR, STD_CMAP, UNKNOWN_GREY, geo_ticks, render_slice

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


def plot_slice(grid: Grid, alt_m: float, component: str, path, title: str = "", origin=None) -> Path:
    """Mean and std of ``component`` (e, n, u) at the grid level nearest ``alt_m``, as the
    web map draws them: the mean grey where no data is within the kernel's reach (only the
    prior is there), the std dark where the map can be trusted; ``origin`` (lat, lon):
    latitude and longitude ticks too."""
    plt = _pyplot()
    c, k = COMPONENTS[component], _level(grid, alt_m)
    extent = [grid.x[0] / 1e3, grid.x[-1] / 1e3, grid.y[0] / 1e3, grid.y[-1] / 1e3]
    fig, axes = plt.subplots(1, 2, figsize=(13, 6.0), constrained_layout=True)
    mean = np.ma.masked_array(grid.mean[:, :, k, c].T, ~grid.known[:, :, k].T)
    std = grid.std[:, :, k, c].T
    limit = float(np.abs(mean).max()) if mean.count() else 1.0
    for ax, values, cmap, label, kw in (
        (
            axes[0],
            mean,
            "RdBu_r",
            f"mean v{component} [m/s] (red: towards east)",
            {"vmin": -limit, "vmax": limit},
        ),
        (axes[1], std, STD_CMAP, f"predictive std of v{component} [m/s] (dark: trustworthy)", {}),
    ):
        cmap = plt.get_cmap(cmap).with_extremes(bad=UNKNOWN_GREY)
        im = ax.imshow(values, origin="lower", extent=extent, cmap=cmap, aspect="equal", **kw)
        fig.colorbar(im, ax=ax, label=label, shrink=0.85)
        _frame(ax, origin)
    axes[0].legend(handles=[_unknown_patch()], loc="lower left", fontsize=8, framealpha=0.85)
    axes[0].set_title(f"{title} mean v{component} at {grid.z[k]:.0f} m (region ENU up)")
    axes[1].set_title(f"{title} uncertainty at {grid.z[k]:.0f} m")
    return _save(fig, path)


def plot_arrows(grid: Grid, alt_m: float, path, title: str = "", origin=None) -> Path:
    """Horizontal mean flow (arrows, faint where no data is within the kernel's reach) over
    the horizontal predictive std at one level, with a key for the arrows' length."""
    plt = _pyplot()
    k = _level(grid, alt_m)
    std = np.hypot(grid.std[:, :, k, 0], grid.std[:, :, k, 1]).T
    fig, ax = plt.subplots(figsize=(8.4, 7.2), constrained_layout=True)
    extent = [grid.x[0] / 1e3, grid.x[-1] / 1e3, grid.y[0] / 1e3, grid.y[-1] / 1e3]
    im = ax.imshow(std, origin="lower", extent=extent, cmap=STD_CMAP, aspect="equal")
    fig.colorbar(
        im, ax=ax, label="predictive std of horizontal velocity [m/s] (dark: trustworthy)", shrink=0.85
    )
    stride = max(len(grid.x) // 25, 1)
    sl = (slice(None, None, stride), slice(None, None, stride), k)
    gx, gy = np.meshgrid(grid.x[::stride] / 1e3, grid.y[::stride] / 1e3, indexing="ij")
    known = grid.known[sl]
    key = None
    for where, alpha in ((known, 1.0), (~known, 0.25)):
        if where.any():
            q = ax.quiver(
                gx[where],
                gy[where],
                grid.mean[sl][..., 0][where],
                grid.mean[sl][..., 1][where],
                color=MODE_COLOUR,
                width=0.003,
                alpha=alpha,
                scale=4000,
                scale_units="width",
            )
            key = key or q
    if key is not None:
        ax.quiverkey(
            key, 0.75, -0.08, 100.0, "100 m/s (faint: no data within reach)", labelpos="E", coordinates="axes"
        )
    _frame(ax, origin)
    ax.set(title=f"{title} mean flow at {grid.z[k]:.0f} m (region ENU up)")
    return _save(fig, path)


def _frame(ax, origin) -> None:
    """ENU km axes from the region's origin, and its latitude and longitude if known."""
    ax.set(xlabel="east of the region's origin [km]", ylabel="north [km]")
    if origin is not None:
        geo_ticks(ax, origin)


def _unknown_patch():
    from matplotlib.patches import Patch

    return Patch(color=UNKNOWN_GREY, label="no data within the kernel's reach (the prior)")


def plot_modes(grid: Grid, alt_m: float, path, title: str = "", min_share: float = 0.05, origin=None) -> Path:
    """Each traffic class with at least ``min_share`` of the traffic as an arrow along its
    mode's horizontal mean (one colour: its direction is the heading), wider with its share,
    over the mixture's speed (a grid fetched with ``modes=True``)."""

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
        origin=origin,
    )
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(png)
    return path


def plot_tube(tubes: Tubes, max_std_mps: float, path, title: str = "", origin=None, levels: int = 4) -> Path:
    """The tube as maps at ``levels`` altitudes (the lowest and highest of it at or above 0 m
    and evenly between): its voxels coloured by their mean vertical velocity, grey where
    the map is outside it. Slices read where a 3D scatter hides depth."""
    plt = _pyplot()
    full = np.full(tubes.mask.shape, np.nan)
    full[tubes.mask] = tubes.mean[:, 2]  # the points are the mask's voxels, in its C order
    held = np.flatnonzero(tubes.mask.any(axis=(0, 1)) & (tubes.z >= 0))
    if not len(held):
        raise ValueError(f"no voxel of the tube std < {max_std_mps:g} m/s lies at or above 0 m")
    picks = np.unique(np.round(np.linspace(held[0], held[-1], levels)).astype(int))
    limit = float(np.nanmax(np.abs(full[..., picks]))) if np.isfinite(full[..., picks]).any() else 1.0
    extent = [tubes.x[0] / 1e3, tubes.x[-1] / 1e3, tubes.y[0] / 1e3, tubes.y[-1] / 1e3]
    cols = min(len(picks), 2)
    rows = -(-len(picks) // cols)
    fig, axes = plt.subplots(
        rows, cols, figsize=(6.2 * cols, 5.6 * rows), constrained_layout=True, squeeze=False
    )
    cmap = plt.get_cmap("coolwarm").with_extremes(bad=UNKNOWN_GREY)
    for ax, k in zip(axes.flat, picks, strict=False):
        im = ax.imshow(
            np.ma.masked_invalid(full[:, :, k].T),
            origin="lower",
            extent=extent,
            cmap=cmap,
            vmin=-limit,
            vmax=limit,
            aspect="equal",
        )
        share = tubes.mask[:, :, k].mean()
        ax.set_title(f"{tubes.z[k]:.0f} m: {100 * share:.0f} % of the level in the tube", fontsize=10)
        _frame(ax, origin)
    for ax in list(axes.flat)[len(picks) :]:
        ax.set_axis_off()
    fig.colorbar(im, ax=axes, label="mean vertical velocity in the tube [m/s] (grey: outside it)", shrink=0.8)
    fig.suptitle(f"{title} tube: every std component < {max_std_mps:.1f} m/s")
    return _save(fig, path)
