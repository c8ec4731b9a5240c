"""The rules tried for how a known heading narrows its modes' noise (2026-11-28), against the
one kept (:func:`bdf.sectors.heading_mode`): reproduces the RESULTS row "the mode of a
heading, each mode's noise across the track narrowed ...".

    python bench/history/heading-noise-rules.py

Held-out rows scored at their own heading (:meth:`bdf.posterior.Modes.flown`'s rows) with
each rule's std; the mean is the plain pool's for all. On the Paris flight split (the demo's
lattice, raw rows with track and t, 16 sectors), and on the synthetic flows of
``tests/bdf/test_sectors.py`` (a drone corridor across a sector boundary at 16 sectors,
headings flown every way at 8). Also the plain pool's root mean square standardised error
along, across each row's heading and up (Paris): where its std was too wide.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

from bdf import metrics  # noqa: E402
from bdf.sectors import HEADING_NOISE_CAP, Sectors, heading_mode  # noqa: E402


def sector_width(sectors, heading, weight, m0, s0, n0, m1, s1, n1):
    """Rejected: each mode loses the spread of headings uniform over its sector's width."""
    width_sq = np.radians(360.0 / sectors.directions) ** 2
    stds = []
    for m, s, n in ((m0, s0, n0), (m1, s1, n1)):
        across = np.stack([m[:, 1] ** 2, m[:, 0] ** 2, 0 * m[:, 0]], axis=1) * width_sq / 12
        stds.append(np.sqrt(s**2 - np.minimum(across, HEADING_NOISE_CAP * n)))
    return heading_mode(sectors, heading, weight, m0, stds[0], 0 * n0, m1, stds[1], 0 * n1)[1]


def kappa_alone(sectors, heading, weight, m0, s0, n0, m1, s1, n1):
    """Rejected: the kept rule without its cap by the spread of headings between the two
    modes' directions."""
    w = weight[:, None]
    a0, a1 = 1 / s0**2, 1 / s1**2
    precision = w * a0 + (1 - w) * a1
    mean = (w * a0 * m0 + (1 - w) * a1 * m1) / precision
    turn = a0 * a1 * (m0 - m1) / precision**2
    e, n = mean[:, 0], mean[:, 1]
    kappa = np.clip(
        (e * turn[:, 1] - n * turn[:, 0]) / (np.radians(360 / sectors.directions) * (e * e + n * n)), 0, 1
    )
    h = np.radians(heading)
    across = np.stack([np.cos(h) ** 2, np.sin(h) ** 2, 0 * h], axis=1)
    variances = []
    for s, noise in ((s0, n0), (s1, n1)):
        told = (1 - (1 - kappa) ** 2)[:, None] * across * (noise * across).sum(axis=1, keepdims=True)
        variances.append(s**2 - np.minimum(told, HEADING_NOISE_CAP * noise))
    return 1 / np.sqrt(w / variances[0] + (1 - w) / variances[1])


def scores(name, modes, sectors, V, mu, sd) -> tuple[np.ndarray, np.ndarray]:
    """Each rule's cov95 and MSLL printed; the plain pool's mean and std returned."""
    heading = np.degrees(np.arctan2(V[:, 0], V[:, 1]))
    k0, k1, weight = sectors.nearest_two(heading)
    rows = np.arange(len(V))
    parts = [a[rows, k] for k in (k0, k1) for a in (modes.mean, modes.std, modes.heading_noise)]
    slow = (sectors.classify(V) == sectors.directions)[:, None]
    plain = modes._replace(heading_noise=np.zeros_like(modes.heading_noise)).flown(sectors, V)
    rules = {
        "plain pool": plain[1],
        "sector's width": sector_width(sectors, heading, weight, *parts),
        "kappa alone": kappa_alone(sectors, heading, weight, *parts),
        "kept (heading_mode)": modes.flown(sectors, V)[1],
    }
    for rule, std in rules.items():
        std = np.where(slow, modes.std[:, -1], std)
        print(
            f"{name:40s} {rule:20s} cov95 {metrics.coverage(V, plain[0], std):.4f} "
            f"MSLL {metrics.msll(V, plain[0], std, mu, sd):.3f}",
            flush=True,
        )
    return plain


def main() -> None:
    from bench_tracks import library_map, split

    from clients import samples
    from tests.bdf.test_sectors import field, flows

    for kind, S in (("corridor", 16), ("every heading", 8)):
        X, V = flows(kind, 3000, 0)
        Xt, Vt = flows(kind, 3000, 1)
        scores(
            f"synthetic, {kind}, {S} sectors",
            field(S).fit(X, V).predict_modes(Xt),
            Sectors(S),
            Vt,
            V.mean(0),
            V.std(0),
        )
    train, test, lower, upper = split()
    spec = samples.paris_demo_region(lower, upper, directions=16)
    rmap = library_map(spec, train, True)
    mean, std = scores(
        "Paris flight split, 16 sectors",
        rmap.predict_modes(test.X),
        spec.sectors,
        test.V,
        train.V.mean(0),
        train.V.std(0),
    )
    h = np.radians(np.degrees(np.arctan2(test.V[:, 0], test.V[:, 1])))
    r = test.V - mean
    fast = np.hypot(test.V[:, 0], test.V[:, 1]) >= spec.sectors.slow_mps
    for what, u in (("along", (np.sin(h), np.cos(h))), ("across", (np.cos(h), -np.sin(h)))):
        err = r[:, 0] * u[0] + r[:, 1] * u[1]
        sd_u = np.sqrt(std[:, 0] ** 2 * u[0] ** 2 + std[:, 1] ** 2 * u[1] ** 2)
        rms = np.sqrt(np.mean((err / sd_u)[fast] ** 2))
        print(f"plain pool, Paris: RMS standardised error {what} the heading {rms:.3f}")
    rms = np.sqrt(np.mean((r[fast, 2] / std[fast, 2]) ** 2))
    print(f"plain pool, Paris: RMS standardised error up {rms:.3f}")


if __name__ == "__main__":
    main()
