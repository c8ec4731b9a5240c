"""PNG pictures of one horizontal slice of a map, for the viewer page and for humans.

Rendered with matplotlib's object API (a ``Figure`` per request, no pyplot state), so
request threads can render at once. Every picture carries its colour scale and units.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Literal

import numpy as np
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from bdf.grid import axis_counts
from bdf.sectors import MIN_SHARE

Layer = Literal["mean", "std", "tube", "modes", "share"]
#: Arrows per horizontal axis on the modes layer.
ARROWS_PER_SIDE = 24
Component = Literal["e", "n", "u"]


@dataclass(frozen=True)
class SliceView:
    """What a slice draws: the layer, the component, the tube's bound and the least share
    of a drawn mode."""

    layer: Layer
    component: Component
    max_std_mps: float
    min_share: float


COMPONENTS = ("e", "n", "u")
#: uncertainty as the web map draws it: dark where the map can be trusted, pale where not
STD_CMAP = "YlGnBu_r"
#: cells with no data within the kernel's reach (the prior), or outside the tube
UNKNOWN_GREY = "0.85"
#: arrows of the flow and of the modes (one colour: an arrow's direction is its heading)
MODE_COLOUR = "#c2185b"
MAX_SIDE = 256  # cells per horizontal axis of a slice: enough for a screen, cheap to predict


def slice_axes(lower, upper, spacing, bbox: tuple[float, float, float, float] | None, step: float | None):
    """Horizontal axes ``(x, y)`` of a slice: the bbox (default: the region) sampled at
    ``step`` metres (default: a quarter of the hinge spacing, coarser if that would give
    more than ``MAX_SIDE`` cells per axis). Raises ``ValueError`` on a bad bbox or step."""
    lo, hi = np.asarray(lower[:2], float), np.asarray(upper[:2], float)
    if bbox is not None:
        box = np.asarray(bbox, float)
        if np.any(box[2:] <= box[:2]):
            raise ValueError(f"bbox {box.tolist()} must have xmax > xmin and ymax > ymin")
        if np.any(box[:2] < lo) or np.any(box[2:] > hi):
            raise ValueError(
                f"bbox {box.tolist()} leaves the region's x, y bounds {lo.tolist()} .. {hi.tolist()}"
            )
        lo, hi = box[:2], box[2:]
    if step is None:
        step = max(min(spacing[:2]) / 4, float(np.max(hi - lo)) / (MAX_SIDE - 1))
    if not step > 0:
        raise ValueError(f"step must be positive, got {step}")
    counts = axis_counts(lo, hi, step)
    if not np.all(counts <= MAX_SIDE):
        raise ValueError(
            f"a slice of {counts.tolist()} cells exceeds {MAX_SIDE} per axis: "
            "use a larger step or a smaller bbox"
        )
    # the last point may pass hi by rounding (far from the origin): it is hi
    return tuple(np.minimum(lo[d] + step * np.arange(int(counts[d])), hi[d]) for d in (0, 1))


def render_slice(
    x: np.ndarray,
    y: np.ndarray,
    mean: np.ndarray,
    std: np.ndarray,
    known: np.ndarray,
    *,
    alt_m: float,
    layer: Layer,
    component: Component,
    max_std_mps: float,
    title: str,
    share: np.ndarray | None = None,
    share_std: np.ndarray | None = None,
    mode_mean: np.ndarray | None = None,
    mode_known: np.ndarray | None = None,
    min_share: float = MIN_SHARE,
    origin: tuple[float, float] | None = None,
) -> bytes:
    """PNG of one slice. ``mean``, ``std``: (nx, ny, 3) m/s; ``known``: (nx, ny);
    ``share`` (nx, ny, C), ``share_std`` (nx, ny), ``mode_mean`` (nx, ny, C, 3) and
    ``mode_known`` (nx, ny, C: the class has data within the kernel's reach): each traffic
    class's.

    ``mean``: the mean of ``component``, grey where no data is within the kernel's reach
    (the prior);
    ``std``: its predictive std; ``tube``: the mean where every component's std is below
    ``max_std_mps`` and there is data, grey elsewhere; ``share``: the largest class's share
    (1: one direction; low: mixed traffic); ``modes``: an arrow per class with at least
    ``min_share`` of the traffic and data of its own within the kernel's reach (elsewhere a
    mode is only its prior: the class's mean velocity near there), along its
    horizontal mean, as wide as its share, faint where that share is less than one std above
    ``min_share``, on the horizontal speed of the mixture. ``origin`` (lat, lon): latitude
    and longitude ticks too (:func:`geo_ticks`).
    """
    c = COMPONENTS.index(component)
    if layer in ("modes", "share") and share is None:
        raise ValueError(f"the {layer} layer needs the modes")
    if mode_known is None and share is not None:
        mode_known = np.broadcast_to(known[..., None], share.shape)
    if layer == "share":
        values = np.ma.array(share.max(axis=-1), mask=~known)
        cmap, norm = "viridis", Normalize(1.0 / share.shape[-1], 1.0)
        label = "share of the largest traffic class"
    elif layer == "modes":
        values = np.ma.array(np.hypot(mean[..., 0], mean[..., 1]), mask=~known)
        cmap, norm = "Greys", Normalize(0.0, 2.0 * _robust_max(values))
        label = "horizontal speed of the mixture [m/s]"
    elif layer == "std":
        values = np.ma.masked_invalid(std[..., c])
        cmap, norm = STD_CMAP, Normalize(float(values.min()), _robust_max(values))
        label = f"predictive std of v{component} [m/s] (dark: trustworthy)"
    else:
        hide = ~known if layer == "mean" else ~(known & (std < max_std_mps).all(axis=-1))
        values = np.ma.array(mean[..., c], mask=hide)
        limit = _robust_max(np.abs(values))
        cmap, norm = "RdBu_r", Normalize(-limit, limit)
        label = f"mean v{component} [m/s]"
    fig = Figure(figsize=(7.2, 6.4), layout="constrained")
    ax = fig.add_subplot()
    ax.set_facecolor(UNKNOWN_GREY)  # masked cells: no data, or outside the tube
    extent = [x[0] / 1e3, x[-1] / 1e3, y[0] / 1e3, y[-1] / 1e3]
    im = ax.imshow(values.T, origin="lower", extent=extent, cmap=cmap, norm=norm, aspect="equal")
    fig.colorbar(im, ax=ax, label=label, shrink=0.9, extend="max" if layer == "std" else "both")
    handles = []
    if layer == "modes":
        handles = _mode_arrows(ax, x, y, share, share_std, mode_mean, mode_known, min_share)
    if layer != "std":
        grey = "no data within the kernel's reach" if layer != "tube" else "no data, or outside the tube"
        handles.append(Patch(color=UNKNOWN_GREY, label=grey))
        ax.legend(handles=handles, loc="lower left", fontsize=7, framealpha=0.85)
    if origin is not None:
        geo_ticks(ax, origin)
    what = {
        "mean": "mean",
        "std": "uncertainty",
        "tube": f"tube (std < {max_std_mps:g} m/s)",
        "modes": f"traffic modes (share >= {min_share:g})",
        "share": "directional purity",
    }[layer]
    ax.set(
        xlabel="east of the region's origin [km]",
        ylabel="north [km]",
        title=f"{title}: {what} at {alt_m:.0f} m (region ENU up)",
    )
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return buf.getvalue()


def _mode_arrows(ax, x, y, share, share_std, mode_mean, mode_known, min_share):
    """An arrow per class and cell (every k-th cell) with at least ``min_share`` of the
    traffic and data of its own (``mode_known``): along the mode's horizontal mean (its
    direction is the heading: one colour, a key for the length), wider as its share grows
    (three widths: below 0.2, to 0.5, above), faint unless the share is at least one std
    above ``min_share``. Returns the legend's handles of the widths drawn."""
    k = max(1, int(np.ceil(max(len(x), len(y)) / ARROWS_PER_SIDE)))
    xs, ys = np.meshgrid(x[::k] / 1e3, y[::k] / 1e3, indexing="ij")
    s, m, seen = share[::k, ::k], mode_mean[::k, ::k], mode_known[::k, ::k]
    speed = np.hypot(m[..., 0], m[..., 1])
    cell_km = k * float(x[1] - x[0]) / 1e3 if len(x) > 1 else 1.0
    scale = max(float(np.max(speed[seen & (s >= min_share)], initial=0.0)), 1e-9) / (0.9 * cell_km)
    show = seen & (s >= min_share) & (speed > 0)
    sure = s - share_std[::k, ::k, None] >= min_share
    key = None
    for low, high, width in ((min_share, 0.2, 0.002), (0.2, 0.5, 0.004), (0.5, 1.01, 0.007)):
        for established, alpha in ((False, 0.25), (True, 1.0)):
            pick = show & (s >= low) & (s < high) & (sure == established)
            if pick.any():
                cells = np.nonzero(pick)
                key = ax.quiver(
                    xs[cells[:2]],
                    ys[cells[:2]],
                    m[..., 0][pick],
                    m[..., 1][pick],
                    color=MODE_COLOUR,
                    angles="xy",
                    scale_units="xy",
                    scale=scale,
                    width=width,
                    alpha=alpha,
                    label=f"a mode with {low:g} to {min(high, 1):g} of the traffic" if established else None,
                )
    if key is not None:
        speed_key = float(np.round(0.5 * scale * cell_km, -1)) or 10.0
        ax.quiverkey(key, 0.86, -0.085, speed_key, f"{speed_key:g} m/s", labelpos="E", coordinates="axes")
    return ax.get_legend_handles_labels()[0]


def geo_ticks(ax, origin: tuple[float, float]) -> None:
    """Longitude and latitude ticks on the top and right of axes in ENU km from ``origin``
    (lat, lon): exact along the axes through the origin (pyproj), where the web map's
    graticule crosses them."""
    from bdf.frames import ENUFrame

    frame, km = ENUFrame(*origin), np.linspace(-500.0, 500.0, 2001)
    zeros = np.zeros_like(km)
    lon = frame.to_geodetic(np.column_stack([km * 1e3, zeros, zeros]))[:, 1]
    lat = frame.to_geodetic(np.column_stack([zeros, km * 1e3, zeros]))[:, 0]
    top = ax.secondary_xaxis(
        "top", functions=(lambda x: np.interp(x, km, lon), lambda v: np.interp(v, lon, km))
    )
    right = ax.secondary_yaxis(
        "right", functions=(lambda y: np.interp(y, km, lat), lambda v: np.interp(v, lat, km))
    )
    top.set_xlabel("longitude [deg E]", fontsize=8)
    right.set_ylabel("latitude [deg N]", fontsize=8)


def _robust_max(values: np.ma.MaskedArray) -> float:
    """The colour scale's top: the 99th percentile, so that a few outliers do not wash out
    the rest (they show in the end colour; the bar's arrow says so)."""
    shown = values.compressed()
    top = float(np.percentile(shown, 99)) if len(shown) else 0.0
    return top if top > 0 else 1.0
