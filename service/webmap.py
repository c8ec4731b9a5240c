"""The map as a web map draws it: XYZ raster tiles in Web Mercator, and the flows at an
altitude as GeoJSON arrows.

A tile is 256 x 256 pixels at altitude ``alt_m`` above the WGS84 ellipsoid (what a pilot
reads; the region's ENU "up" differs from it by the earth's curvature, 125 m at 40 km
from the origin). The map is answered exactly at the 65 x 65 corners of 4 x 4 pixel
blocks and interpolated bilinearly between them (the map's structure is kilometres
across: at the zooms a region fills, a block is tens to hundreds of metres); outside the
region the tile is transparent. Colour scales are fixed per layer (``vmax``), so
neighbouring tiles agree and one legend serves the view (:data:`LAYERS`).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import Literal

import contourpy
import numpy as np
from matplotlib import colormaps
from matplotlib.colors import to_hex
from matplotlib.image import imsave

TILE_PX = 256
#: the map is answered at every BLOCK_PX-th pixel corner, interpolated between
BLOCK_PX = 4
SAMPLES = TILE_PX // BLOCK_PX + 1
#: the deepest zoom served: a pixel of about 2 m at the equator
MAX_ZOOM = 22
#: opacity of the pixels where the map is not ``known`` (its prior shows, faded)
UNKNOWN_ALPHA = 0.35

Layer = Literal["speed", "std", "known", "share"]


@dataclass(frozen=True)
class LayerStyle:
    """How a layer is coloured: a matplotlib colour map over 0 .. vmax (default
    ``default_vmax``), in ``unit``, described as ``label`` (the legend's)."""

    cmap: str
    default_vmax: float
    unit: str
    label: str


LAYERS: dict[str, LayerStyle] = {
    "speed": LayerStyle("viridis", 300.0, "m/s", "horizontal speed of the mean velocity"),
    "std": LayerStyle("YlOrRd", 60.0, "m/s", "predictive std, the largest of east, north and up"),
    "known": LayerStyle("Greens", 1.0, "", "where data within the kernel's reach support the map"),
    "share": LayerStyle("Purples", 1.0, "", "share of the busiest traffic class (heading sector)"),
}


def legends() -> dict:
    """What the viewer's legend draws per layer: colours along the scale, ticks, unit, label."""
    out = {}
    for name, style in LAYERS.items():
        colours = colormaps[style.cmap](np.linspace(0.0, 1.0, 11))
        out[name] = {
            "colours": [to_hex(c) for c in colours],
            "ticks": [f"{t:g}" for t in np.linspace(0.0, style.default_vmax, 5)]
            if style.unit
            else ["no", "yes"],
            "unit": style.unit,
            "label": style.label,
        }
    return out


def tile_lonlat(z: int, x: int, y: int, n: int = SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """Longitudes (n,) and latitudes (n,) of an ``n`` x ``n`` lattice spanning the tile's
    pixel corners, west to east and north to south. ``ValueError`` for a tile that does
    not exist."""
    if not (0 <= z <= MAX_ZOOM and 0 <= x < 2**z and 0 <= y < 2**z):
        raise ValueError(f"tile {z}/{x}/{y} does not exist: zoom 0 .. {MAX_ZOOM}, x and y 0 .. 2^zoom - 1")
    t = np.linspace(0.0, 1.0, n)
    lon = (x + t) / 2**z * 360.0 - 180.0
    lat = np.degrees(np.arctan(np.sinh(np.pi * (1.0 - 2.0 * (y + t) / 2**z))))
    return lon, lat


def tile_points(spec, z: int, x: int, y: int, alt_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The ENU points (m, 3) of the tile's sample lattice at ``alt_m`` that lie inside the
    region, and the mask (n, n) of those samples (rows north to south)."""
    lon, lat = tile_lonlat(z, x, y)
    LON, LAT = np.meshgrid(lon, lat)
    X = spec.frame().to_enu(LAT.ravel(), LON.ravel(), np.full(LAT.size, float(alt_m)))
    inside = spec.inside(X)
    return X[inside], inside.reshape(LAT.shape)


def values(layer: Layer, mean: np.ndarray, std: np.ndarray, known: np.ndarray, share=None) -> np.ndarray:
    """The quantity ``layer`` draws at each answered point."""
    if layer == "speed":
        return np.hypot(mean[:, 0], mean[:, 1])
    if layer == "std":
        return std.max(axis=1)
    if layer == "known":
        return known.astype(float)
    return share.max(axis=1)


def _interpolation() -> np.ndarray:
    """(TILE_PX, SAMPLES): each pixel centre's bilinear weights on the sample lattice's axis."""
    centres = (np.arange(TILE_PX) + 0.5) / BLOCK_PX
    lo = np.minimum(centres.astype(int), SAMPLES - 2)
    w = centres - lo
    A = np.zeros((TILE_PX, SAMPLES))
    A[np.arange(TILE_PX), lo] = 1.0 - w
    A[np.arange(TILE_PX), lo + 1] = w
    return A


#: the same for every tile: made once
INTERPOLATION = _interpolation()


def _upsample(grid: np.ndarray) -> np.ndarray:
    """The sample lattice (SAMPLES, SAMPLES) to pixel centres (TILE_PX, TILE_PX), bilinear."""
    return INTERPOLATION @ grid @ INTERPOLATION.T


def render_tile(layer: Layer, inside: np.ndarray, value: np.ndarray, known: np.ndarray, vmax: float) -> bytes:
    """The tile as an RGBA PNG: ``value`` (at the samples ``inside``) on the layer's colour
    scale over 0 .. ``vmax``, faded where not ``known``, transparent outside the region."""
    style = LAYERS[layer]
    filled = np.zeros(inside.shape)
    filled[inside] = value
    trusted = np.zeros(inside.shape)
    trusted[inside] = known
    # outside samples carry the nearest inside value's weight 0 through the coverage
    coverage = _upsample(inside.astype(float))
    with np.errstate(invalid="ignore", divide="ignore"):
        pixel = _upsample(filled) / coverage
        pixel_known = _upsample(trusted) / coverage
    rgba = colormaps[style.cmap](np.clip(np.nan_to_num(pixel) / vmax, 0.0, 1.0))
    if layer == "known":
        rgba[..., 3] = np.where(pixel_known >= 0.5, 0.6, 0.15)
    else:
        rgba[..., 3] = np.where(pixel_known >= 0.5, 0.85, UNKNOWN_ALPHA)
    rgba[coverage < 0.5, 3] = 0.0
    out = io.BytesIO()
    imsave(out, (rgba * 255).round().astype(np.uint8), format="png")
    return out.getvalue()


def outline(spec) -> np.ndarray:
    """The region's horizontal boundary at its lowest altitude: a closed ring (65, 2) of
    [lon, lat], 16 points an edge (its edges are straight in ENU, curved on the map)."""
    (x0, y0, z0), (x1, y1, _) = spec.lower, spec.upper
    t = np.linspace(0.0, 1.0, 16, endpoint=False)
    ring = np.concatenate(
        [
            np.stack([x0 + (x1 - x0) * t, np.full(16, y0)], 1),
            np.stack([np.full(16, x1), y0 + (y1 - y0) * t], 1),
            np.stack([x1 - (x1 - x0) * t, np.full(16, y1)], 1),
            np.stack([np.full(16, x0), y1 - (y1 - y0) * t], 1),
            [[x0, y0]],
        ]
    )
    geo = spec.frame().to_geodetic(np.column_stack([ring, np.full(len(ring), z0)]))
    return geo[:, [1, 0]]


def geodetic_bounds(spec) -> tuple[tuple[float, float], tuple[float, float]]:
    """The region's latitude and longitude ranges (of its :func:`outline`)."""
    ring = outline(spec)
    return (ring[:, 1].min(), ring[:, 1].max()), (ring[:, 0].min(), ring[:, 0].max())


def lattice(spec, alt_m: float, step_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A latitude/longitude lattice over the region, about ``step_m`` apart, at ``alt_m``
    above the ellipsoid: its longitudes (nx,), latitudes (ny,), ENU points of the lattice
    (ny * nx, 3; latitude rows) and which of them lie inside the region."""
    frame = spec.frame()
    (lat0, lat1), (lon0, lon1) = geodetic_bounds(spec)
    dlat = step_m / 111_320.0
    dlon = dlat / max(np.cos(np.radians(frame.lat)), 1e-6)
    lon = np.arange(lon0, lon1 + dlon, dlon)
    lat = np.arange(lat0, lat1 + dlat, dlat)
    LON, LAT = np.meshgrid(lon, lat)
    X = frame.to_enu(LAT.ravel(), LON.ravel(), np.full(LAT.size, float(alt_m)))
    return lon, lat, X, spec.inside(X)


def tube_outline_geojson(lon, lat, inside, std_max: np.ndarray, max_std_mps: float) -> dict:
    """The outline of the tube at one altitude (where the largest std component is below
    ``max_std_mps``) on the :func:`lattice` ``lon`` x ``lat``: contour lines
    (contourpy, matplotlib's own), as one MultiLineString of [lon, lat]."""
    field = np.full(inside.shape, 2.0 * max_std_mps)  # outside the region: outside the tube
    field[inside] = std_max
    lines = contourpy.contour_generator(lon, lat, field.reshape(len(lat), len(lon))).lines(max_std_mps)
    coordinates = [np.round(line, 7).tolist() for line in lines if len(line) > 1]
    feature = {
        "type": "Feature",
        "geometry": {"type": "MultiLineString", "coordinates": coordinates},
        "properties": {"max_std_mps": max_std_mps, "inside": float(np.mean(field < max_std_mps))},
    }
    return {"type": "FeatureCollection", "features": [feature]}


def flows_geojson(spec, X: np.ndarray, pred, min_share: float, arrow_s: float) -> dict:
    """Arrows of the flows at the points ``X`` (of a :func:`lattice`): at each, each mode
    of share at least ``min_share`` (one class: the mean), from the point along its
    horizontal velocity for ``arrow_s`` seconds, with a head; properties: speed (m/s),
    heading (degrees from north), share, known."""
    if pred.modes is not None:
        share, mean, known = pred.modes.share, pred.modes.mean, ~pred.modes.prior_only
    else:
        share, mean, known = np.ones((len(X), 1)), pred.mean[:, None], pred.known[:, None]
    rows, classes = np.nonzero(share >= min_share)
    v = mean[rows, classes, :2]
    start = X[rows]
    tip = start.copy()
    tip[:, :2] += v * arrow_s
    # the head: two barbs a quarter of the arrow long, 25 degrees either side of its back
    back = -v * arrow_s * 0.25
    barbs = []
    for angle in (np.radians(25.0), -np.radians(25.0)):
        c, s = np.cos(angle), np.sin(angle)
        barb = tip.copy()
        barb[:, 0] += c * back[:, 0] - s * back[:, 1]
        barb[:, 1] += s * back[:, 0] + c * back[:, 1]
        barbs.append(barb)
    frame = spec.frame()
    geo = [frame.to_geodetic(p)[:, [1, 0]].round(7) for p in (start, tip, *barbs)]
    speed = np.hypot(v[:, 0], v[:, 1])
    heading = np.degrees(np.arctan2(v[:, 0], v[:, 1])) % 360.0
    features = [
        {
            "type": "Feature",
            "geometry": {
                "type": "MultiLineString",
                "coordinates": [
                    [geo[0][i].tolist(), geo[1][i].tolist()],
                    [geo[2][i].tolist(), geo[1][i].tolist(), geo[3][i].tolist()],
                ],
            },
            "properties": {
                "speed_mps": round(float(speed[i]), 2),
                "heading_deg": round(float(heading[i]), 1),
                "share": round(float(share[rows[i], classes[i]]), 4),
                "known": bool(known[rows[i], classes[i]]),
            },
        }
        for i in range(len(rows))
        if speed[i] > 0
    ]
    return {"type": "FeatureCollection", "features": features}
