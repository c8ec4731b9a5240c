"""Demo on real ADS-B traffic: learn the Paris velocity map, report its accuracy, plot slices."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from bdf import BayesianDynamicField, ingest, metrics

log = logging.getLogger(__name__)

#: The grid the benchmark uses (bench/RESULTS.md), picked by hand (see its note on the grid).
PARIS_SPACING_M = np.array([4000.0, 4000.0, 1000.0])
PARIS_GAMMA = 1.0 / PARIS_SPACING_M**2


def run(out: Path, altitudes_m=(1000.0, 3000.0)) -> dict:
    obs, lower, upper = ingest.load_paris()
    test = ingest.train_test_split(obs, by="flight", test_fraction=0.2, seed=0)
    field = BayesianDynamicField(lower, upper, PARIS_SPACING_M, PARIS_GAMMA, alpha="auto", beta="auto")
    t0 = time.perf_counter()
    # each flight counts once per grid cell it crosses: 1 Hz samples are not independent
    weight = ingest.track_weights(obs.subset(~test), PARIS_SPACING_M)
    field.fit(obs.X[~test], obs.V[~test], sample_weight=weight)
    mean, std = field.predict(obs.X[test], return_std=True)
    seconds = time.perf_counter() - t0
    train = obs.V[~test]
    report = {
        "train points": int((~test).sum()),
        "test points (held-out flights)": int(test.sum()),
        "hinges M": len(field.hinges),
        "fit + test query [s]": round(seconds, 2),
        "RMSE [m/s]": round(float(metrics.rmse(obs.V[test], mean)), 2),
        "MSLL": round(float(metrics.msll(obs.V[test], mean, std, train.mean(0), train.std(0))), 3),
        "95% coverage": round(float(metrics.coverage(obs.V[test], mean, std)), 3),
        "fitted noise std per component [m/s]": np.round(1 / np.sqrt(field.beta_), 2).tolist(),
    }
    width = max(map(len, report))
    print("Paris velocity map (real ADS-B from the OpenSky Network, via the `traffic` package)")
    for key, value in report.items():
        print(f"  {key:<{width}}  {value}")
    out.mkdir(parents=True, exist_ok=True)
    for alt in altitudes_m:
        path = out / f"paris_slice_{int(alt)}m.png"
        plot_slice(field, lower, upper, alt, path, data=obs.X[np.abs(obs.X[:, 2] - alt) < 150])
        print(f"  wrote {path}")
    return report


def plot_slice(field, lower, upper, alt_m, path, data=None, n=160):
    """Horizontal slice at ``alt_m``: mean speed with flow arrows, and the predictive std."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs, ys = np.linspace(lower[0], upper[0], n), np.linspace(lower[1], upper[1], n)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, alt_m)], 1)
    mean, std = field.predict(pts, return_std=True)
    speed = np.hypot(mean[:, 0], mean[:, 1]).reshape(gx.shape)
    horizontal_std = np.sqrt(std[:, 0] ** 2 + std[:, 1] ** 2).reshape(gx.shape)
    km = 1e-3
    extent = [lower[0] * km, upper[0] * km, lower[1] * km, upper[1] * km]
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.6), constrained_layout=True)
    im = axes[0].imshow(speed, origin="lower", extent=extent, cmap="viridis")
    step = n // 20
    axes[0].quiver(
        gx[::step, ::step] * km,
        gy[::step, ::step] * km,
        mean[:, 0].reshape(gx.shape)[::step, ::step],
        mean[:, 1].reshape(gx.shape)[::step, ::step],
        color="white",
        width=0.003,
    )
    fig.colorbar(im, ax=axes[0], label="mean horizontal speed [m/s]")
    axes[0].set_title(f"mean flow at {alt_m:.0f} m")
    im = axes[1].imshow(horizontal_std, origin="lower", extent=extent, cmap="magma_r")
    if data is not None and len(data):
        axes[1].scatter(
            data[:, 0] * km, data[:, 1] * km, s=0.2, c="cyan", alpha=0.4, label="observations ±150 m"
        )
        axes[1].legend(loc="upper right", markerscale=20)
    fig.colorbar(im, ax=axes[1], label="predictive std of horizontal velocity [m/s]")
    axes[1].set_title(f"uncertainty at {alt_m:.0f} m")
    for ax in axes:
        ax.set_xlabel("east [km]")
        ax.set_ylabel("north [km]")
    fig.savefig(path, dpi=110)
    plt.close(fig)
