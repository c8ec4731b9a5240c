"""Core benchmark on real ADS-B traffic around Paris: bdf vs the paper's algorithm vs an exact GP.

    .venv/bin/python bench/bench_core.py [--gp-points 2000] [--skip-reference] [--cv]
        [--splits point flight] [--no-append]
    .venv/bin/python bench/bench_core.py --directions 1,4,8,12 [--splits ...]

``--directions``: only the directional maps (``bdf.sectors``), per number of sectors:
the mixture's MSLL (its density), and the conditional given the test point's own class
(its heading sector, or slow): RMSE, MSLL, 95% coverage; fit time, the search's floor
(the same fit with alpha and beta given at the values "auto" found: no search, the same
algebra, in the same threads) and a 100,000-point query of the
modes. ``--soft S`` adds the same for S sectors with soft assignment (each
moving observation split between its two nearest sector centres, linearly in angle;
evidence made here by the library's one function, ``Evidence.from_points``), the
alternative the library does not take.

The sparse GP row (flight split only: it trains for minutes) needs ``pip install -e '.[gp]'``
(PyTorch 2.13.0 CPU and GPyTorch).

Data: the Paris sample (OpenSky via `traffic`), points within 40 km of the mean position
and below 6,000 m. Two splits, seed 0: 20% of points at random; 20% of whole flights.
Every method sees the same train/test arrays in the same run. bdf runs with the global
noise (the paper's model, evidence-fitted per component) and with local noise
(``noise_spacing``, ``bdf.noise``), whose mean is the same. Times are wall-clock on
this machine, best of ``--repeat`` runs for the fast methods. Appends to bench/RESULTS.md.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import importlib.util
import os
import platform
import sys
import time
import uuid
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bdf import BayesianDynamicField, crossval, ingest, metrics
from bdf.kernel import DEFAULT_CUTOFF
from bdf.sectors import Sectors
from bdf.statistics import Evidence, SectorEvidence
from clients import samples
from clients.samples import PARIS_GAMMA, PARIS_NOISE_SPACING_M, PARIS_SPACING_M

PAPER_ALPHA, PAPER_BETA = 1e-2, 1e2
#: The coarsest grid the targets allow (M >= 2,000): where an "auto" fit takes under 1 s.
COARSE_SPACING_M = np.array([5000.0, 5000.0, 1000.0])
#: Grids of the weighted cross-validation (``--cv``).
CV_SPACINGS_M = [PARIS_SPACING_M, COARSE_SPACING_M, np.array([4000.0, 4000.0, 750.0])]
#: Local-noise lattices and prior weights of the noise CV (``--cv``), on the 4 km grid.
CV_NOISE_SPACINGS_M = [
    (500.0, 500.0, 125.0),
    (1000.0, 1000.0, 125.0),
    (1000.0, 1000.0, 250.0),
    (2000.0, 2000.0, 125.0),
]
CV_NOISE_PRIORS = (0.03, 0.1, 0.3)


def accuracy(V_test, V_train, mean, std) -> dict:
    """RMSE, MSLL and 95% coverage: the accuracy columns of every benchmark table."""
    return {
        "RMSE": float(metrics.rmse(V_test, mean)),
        "MSLL": float(metrics.msll(V_test, mean, std, V_train.mean(0), V_train.std(0))),
        "cov95": float(metrics.coverage(V_test, mean, std)),
    }


def score(name, V_test, V_train, mean, std, train_s, query_s, note=""):
    return {
        "method": name,
        "train s": train_s,
        "query s": query_s,
        **accuracy(V_test, V_train, mean, std),
        "note": note,
    }


#: The Paris lattices the service benchmarks run on.
GRIDS = {"core grid": PARIS_SPACING_M.tolist(), "fine grid": [2000.0, 2000.0, 500.0]}


def rows_table(rows: list[dict]) -> str:
    """A markdown table of dict rows, the union of their keys as columns."""
    cols = list(dict.fromkeys(k for r in rows for k in r))
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = []
        for c in cols:
            v = r.get(c, "")
            v = "(not run)" if isinstance(v, float) and np.isnan(v) else v
            if isinstance(v, str):
                cells.append(v)
            elif isinstance(v, int):
                cells.append(f"{v:d}")
            else:  # small values keep their digits (differences from a reference)
                cells.append(f"{v:.3g}" if v and abs(v) < 1e-2 else f"{v:.3f}")
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def arguments(doc: str) -> argparse.ArgumentParser:
    """The options the store benchmarks share: --postgres URL, --no-append."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--postgres", default=os.environ.get("BDF_TEST_POSTGRES_URL"), help="PostgreSQL URL")
    parser.add_argument("--no-append", action="store_true", help="do not append to bench/RESULTS.md")
    return parser


@contextlib.contextmanager
def postgres_schema(url: str):
    """A store URL on a fresh schema of the server at ``url``; the schema is dropped after."""
    schema = f"bench_{uuid.uuid4().hex[:8]}"
    try:
        yield f"{url}?schema={schema}"
    finally:
        import psycopg

        with psycopg.connect(url, autocommit=True) as conn:
            conn.execute(f"DROP SCHEMA IF EXISTS {schema} CASCADE")


def publish(report: list[str], append: bool) -> None:
    """Print the report and append it to bench/RESULTS.md."""
    text = "\n".join(report)
    print(text)
    if append:
        with open(Path(__file__).with_name("RESULTS.md"), "a") as fh:
            fh.write(text + "\n")


def best_of(repeat, fn):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def run_bdf(
    lower, upper, Xtr, Vtr, Xte, alpha, beta, repeat, weight=None, spacing=PARIS_SPACING_M, noise_spacing=None
):
    """Train = statistics + posterior + variance precompute; query = mean and std of the test set.
    Gamma is 1 / spacing^2."""
    gamma = 1.0 / np.asarray(spacing) ** 2

    def train():
        field = BayesianDynamicField(
            lower, upper, spacing, gamma, alpha=alpha, beta=beta, noise_spacing=noise_spacing
        )
        field.fit(Xtr, Vtr, sample_weight=weight)
        field.predict(Xte[:1], return_std=True)  # factorisation and variance density
        return field

    train_s, field = best_of(repeat, train)
    query_s, (mean, std) = best_of(repeat, lambda: field.predict(Xte, return_std=True))
    return field, train_s, query_s, mean, std


def paper_reference(hinges, Xtr, Vtr, Xte, dtype):
    """The published algorithm: dense Phi, a separate posterior per component, explicit inverses."""
    gamma = PARIS_GAMMA.astype(dtype)
    H = hinges.astype(dtype)

    def phi(X):
        X = X.astype(dtype)
        out = np.empty((len(X), len(H)), dtype)
        for a in range(0, len(X), 20_000):
            d2 = (X[a : a + 20_000, None, :] - H[None]) ** 2
            out[a : a + 20_000] = np.exp(-(d2 * gamma).sum(-1))
        return out

    t0 = time.perf_counter()
    P = phi(Xtr)
    posts = []
    for c in range(3):
        precision = PAPER_ALPHA * np.eye(len(H), dtype=dtype) + PAPER_BETA * (P.T @ P)
        sigma = np.linalg.inv(precision)
        posts.append((sigma, PAPER_BETA * sigma @ (P.T @ Vtr[:, c].astype(dtype))))
    train_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    Q = phi(Xte)
    mean = np.stack([Q @ mu for _, mu in posts], 1).astype(float)
    var = np.stack([1 / PAPER_BETA + np.einsum("nm,nm->n", Q @ s, Q) for s, _ in posts], 1)
    query_s = time.perf_counter() - t0
    # the precision the published code effectively used: the inverse of its covariance
    min_eig = float(np.linalg.eigvalsh(np.linalg.inv(posts[0][0].astype(float))).min())
    return train_s, query_s, mean, np.sqrt(np.maximum(var.astype(float), 1e-12)), min_eig


def exact_gp(Xtr, Vtr, Xte, n, seed=0):
    """scikit-learn GP, ARD RBF + white noise, hyperparameters by marginal likelihood, on n points."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    idx = np.random.default_rng(seed).choice(len(Xtr), size=min(n, len(Xtr)), replace=False)
    kernel = ConstantKernel(1.0) * RBF(
        length_scale=PARIS_SPACING_M, length_scale_bounds=(1e2, 1e6)
    ) + WhiteKernel(0.1, noise_level_bounds=(1e-5, 10.0))
    gp = GaussianProcessRegressor(kernel, normalize_y=True, random_state=seed)
    t0 = time.perf_counter()
    gp.fit(Xtr[idx], Vtr[idx])
    train_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    mean, std = gp.predict(Xte, return_std=True)
    query_s = time.perf_counter() - t0
    return train_s, query_s, mean, std if std.ndim == 2 else np.repeat(std[:, None], 3, 1)


def sparse_gp(Xtr, Vtr, Xte, inducing, steps, seed=0):
    """GPyTorch SGPR (Titsias' collapsed bound), ARD RBF, one GP per component, float32
    (GPyTorch's default), inducing points started on a random subset, Adam (lr 0.1);
    inputs and outputs standardised.
    Optional: runs when ``gpytorch`` is installed (``pip install -e '.[gp]'``)."""
    import gpytorch
    import torch

    torch.manual_seed(seed)
    x_mean, x_std, v_mean, v_std = Xtr.mean(0), Xtr.std(0), Vtr.mean(0), Vtr.std(0)
    x = torch.tensor((Xtr - x_mean) / x_std, dtype=torch.float32)
    xq = torch.tensor((Xte - x_mean) / x_std, dtype=torch.float32)

    class SGPR(gpytorch.models.ExactGP):
        def __init__(self, y, likelihood):
            super().__init__(x, y, likelihood)
            self.mean_module = gpytorch.means.ConstantMean()
            rbf = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(ard_num_dims=3))
            start = x[torch.randperm(len(x))[:inducing]].clone()
            self.covar_module = gpytorch.kernels.InducingPointKernel(rbf, start, likelihood)

        def forward(self, z):
            return gpytorch.distributions.MultivariateNormal(self.mean_module(z), self.covar_module(z))

    t0 = time.perf_counter()
    models = []
    for c in range(3):
        y = torch.tensor((Vtr[:, c] - v_mean[c]) / v_std[c], dtype=torch.float32)
        likelihood = gpytorch.likelihoods.GaussianLikelihood()
        model = SGPR(y, likelihood)
        model.train()
        optimizer = torch.optim.Adam(model.parameters(), lr=0.1)
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(likelihood, model)
        for _ in range(steps):
            optimizer.zero_grad()
            loss = -mll(model(x), y)
            loss.backward()
            optimizer.step()
        models.append((model.eval(), likelihood.eval()))
    train_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    mean, std = np.empty((len(Xte), 3)), np.empty((len(Xte), 3))
    with torch.no_grad():
        for c, (model, likelihood) in enumerate(models):
            pred = likelihood(model(xq))
            mean[:, c] = pred.mean.numpy() * v_std[c] + v_mean[c]
            std[:, c] = pred.variance.sqrt().numpy() * v_std[c]
    return train_s, time.perf_counter() - t0, mean, std


def microscopic(repeat=200):
    """A 300-point radar scan, M = 500: partial_fit + prediction at 1,000 points (median ms)."""
    rng = np.random.default_rng(0)
    lower, upper, spacing = np.zeros(3), np.array([45.0, 18.0, 4.0]), np.array([5.0, 2.0, 1.0])
    field = BayesianDynamicField(lower, upper, spacing, 1 / spacing**2, alpha=1.0, beta=4.0)
    assert len(field.hinges) == 500
    field.fit(rng.uniform(lower, upper, (300, 3)), rng.normal(size=(300, 3)))
    Xq = rng.uniform(lower, upper, (1000, 3))
    mean_only, with_std = [], []
    for _ in range(repeat):
        scan, vel = rng.uniform(lower, upper, (300, 3)), rng.normal(size=(300, 3))
        t0 = time.perf_counter()
        field.partial_fit(scan, vel)
        field.predict(Xq)
        mean_only.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        field.partial_fit(scan, vel)
        field.predict(Xq, return_std=True)
        with_std.append(time.perf_counter() - t0)
    return 1e3 * np.median(mean_only), 1e3 * np.median(with_std)


def weighted_cv(
    obs: ingest.Observations,
    lower,
    upper,
    spacings=CV_SPACINGS_M,
    cutoff=DEFAULT_CUTOFF,
    scales=(1.0, 2.0),
    directions=1,
) -> list[dict]:
    """Flight-grouped 5-fold CV (MSLL) of grids and gammas with track weights, on ``obs``.

    Track weights depend on the grid, so each spacing is one :func:`crossval.cross_validate`
    call with its own weights; gamma is each of ``scales`` times 1 / spacing^2.
    """
    rows = []
    for spacing in spacings:
        weight = obs.track_weights(1 / np.asarray(spacing) ** 2)
        t0 = time.perf_counter()
        _, found = crossval.cross_validate(
            obs.X,
            obs.V,
            lower,
            upper,
            [(spacing, scale / spacing**2) for scale in scales],
            groups=obs.flight,
            sample_weight=weight,
            cutoff=cutoff,
            directions=directions,
        )
        seconds = (time.perf_counter() - t0) / len(found)
        rows += [
            {**row, "gamma x spacing^2": row["gamma"][0] * spacing[0] ** 2, "s": seconds} for row in found
        ]
    return rows


def noise_cv(obs: ingest.Observations, lower, upper) -> list[dict]:
    """Flight-grouped 5-fold CV (MSLL) of local-noise lattices and prior weights on the
    4 km grid with track weights, on ``obs``; the first row is the global noise."""
    weight = obs.track_weights(1 / np.asarray(PARIS_SPACING_M) ** 2)
    rows = []
    for noise_spacing, prior in [(None, None)] + [
        (s, p) for s in CV_NOISE_SPACINGS_M for p in CV_NOISE_PRIORS
    ]:
        t0 = time.perf_counter()
        _, (row,) = crossval.cross_validate(
            obs.X,
            obs.V,
            lower,
            upper,
            [(PARIS_SPACING_M, PARIS_GAMMA)],
            groups=obs.flight,
            sample_weight=weight,
            noise_spacing=noise_spacing,
            noise_prior=prior or 0.1,
        )
        rows.append({**row, "noise spacing": noise_spacing, "prior": prior, "s": time.perf_counter() - t0})
        print(rows[-1], flush=True)
    return rows


def noise_cv_table(rows) -> str:
    lines = ["| noise spacing m | prior weight | CV RMSE | CV MSLL | s |", "|---|---|---|---|---|"]
    for r in rows:
        spacing = "global 1/beta" if r["noise spacing"] is None else list(r["noise spacing"])
        prior = "" if r["prior"] is None else f"{r['prior']:g}"
        lines.append(f"| {spacing} | {prior} | {r['rmse']:.2f} | {r['msll']:.3f} | {r['s']:.1f} |")
    return "\n".join(lines)


def cv_table(rows) -> str:
    lines = [
        "| spacing m | gamma x spacing^2 | M | CV RMSE | CV MSLL | s per candidate |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['spacing']} | {r['gamma x spacing^2']:g} | {r['hinges']} | {r['rmse']:.2f} | "
            f"{r['msll']:.3f} | {r['s']:.1f} |"
        )
    return "\n".join(lines)


def table(rows):
    cols = ["method", "train s", "query s", "RMSE", "MSLL", "cov95", "note"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        cells = [
            r[c] if isinstance(r[c], str) else f"{r[c]:.3f}" if abs(r[c]) < 100 else f"{r[c]:.1f}"
            for c in cols
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def soft_evidence(field, X, V, weight):
    """Evidence of ``field``'s classes with each moving observation split between the two
    nearest sector centres (weights linear in angle), the slow ones in the slow class."""
    sectors = Sectors(field.directions)
    S = sectors.directions
    pos = (np.degrees(np.arctan2(V[:, 0], V[:, 1])) % 360.0) / (360.0 / S)
    low, t = np.floor(pos).astype(int) % S, pos - np.floor(pos)
    slow = np.hypot(V[:, 0], V[:, 1]) < sectors.slow_mps
    parts = []
    for c in range(S + 1):
        share = slow * 1.0 if c == S else ~slow * ((low == c) * (1 - t) + ((low + 1) % S == c) * t)
        w = weight * share
        keep = w > 0
        parts.append(Evidence.from_points(field._grid, field._kernel, X[keep], V[keep], None, w[keep]))
    return SectorEvidence(tuple(parts))


def directions_table(obs, lower, upper, split, counts, repeat, soft=0) -> list[str]:
    """Rows of ``--directions`` for one split."""
    test = ingest.train_test_split(obs, by=split, test_fraction=0.2, seed=0)
    Xtr, Vtr, Xte, Vte = obs.X[~test], obs.V[~test], obs.X[test], obs.V[test]
    weight = obs.subset(~test).track_weights(1 / np.asarray(PARIS_SPACING_M) ** 2)
    Q = np.random.default_rng(1).uniform(lower, upper, (100_000, 3))
    M = len(BayesianDynamicField(lower, upper, PARIS_SPACING_M, PARIS_GAMMA).hinges)
    lines = [
        f"Directional maps, {split} split ({len(Xtr)} train, {len(Xte)} test points, track weights, "
        f"alpha = beta = auto, M = {M}):",
        "",
        "| sectors | mixture MSLL | conditional RMSE | conditional MSLL | conditional cov95 | fit [s] "
        "| fit / fit of 1 | fit at the optima found / fit of 1 | 100k-point modes query [s] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    base = None
    for S, assign in [*((S, "hard") for S in counts), *([(soft, "soft")] if soft else [])]:

        def train(S=S, assign=assign, alpha="auto", beta="auto"):
            field = BayesianDynamicField(
                lower, upper, PARIS_SPACING_M, PARIS_GAMMA, alpha, beta, directions=S
            )
            field.fit(Xtr, Vtr, sample_weight=weight)
            if assign == "soft":
                field.set_evidence(soft_evidence(field, Xtr, Vtr, weight))
            field.predict_modes(Xte[:1])  # factorisations and variance densities
            return field

        fit_s, field = best_of(repeat, train)
        base = fit_s if base is None else base
        post = field.posterior_
        floor_s, _ = best_of(repeat, lambda train=train, post=post: train(alpha=post.alpha, beta=post.beta))
        query_s, _ = best_of(repeat, lambda field=field: field.predict_modes(Q))
        modes = field.predict_modes(Xte)
        mix = metrics.mixture_msll(Vte, modes.share, modes.mean, modes.std, Vtr.mean(0), Vtr.std(0))
        own = Sectors(S).classify(Vte)
        rows = np.arange(len(Xte))
        cond = accuracy(Vte, Vtr, modes.mean[rows, own], modes.std[rows, own])
        lines.append(
            f"| {S}{' (soft)' if assign == 'soft' else ''} | {mix:.3f} | {cond['RMSE']:.2f} "
            f"| {cond['MSLL']:.3f} | {cond['cov95']:.3f} "
            f"| {fit_s:.2f} | {fit_s / base:.2f} | {floor_s / base:.2f} | {query_s:.2f} |"
        )
    return lines


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--gp-points", type=int, default=2000, help="training subset of the exact GP (0: skip it)"
    )
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--skip-reference", action="store_true", help="skip the paper's algorithm (slow)")
    parser.add_argument(
        "--cv",
        action="store_true",
        help="weighted, flight-grouped CV of grids and local-noise lattices (flight split)",
    )
    parser.add_argument("--inducing", type=int, default=256, help="inducing points of the sparse GP")
    parser.add_argument(
        "--sgpr-steps", type=int, default=20, help="Adam steps of the sparse GP, per component"
    )
    parser.add_argument(
        "--splits", nargs="+", choices=["point", "flight"], default=["point", "flight"], help="splits to run"
    )
    parser.add_argument(
        "--directions", default="", help="only the directional maps: sector counts, comma-separated"
    )
    parser.add_argument(
        "--soft", type=int, default=0, help="with --directions: soft assignment, this many sectors"
    )
    parser.add_argument("--no-append", action="store_true", help="do not append to bench/RESULTS.md")
    args = parser.parse_args()

    obs, lower, upper = samples.load_paris()
    if args.directions:
        counts = [int(c) for c in args.directions.split(",")]
        report = [
            f"## Directional maps, {datetime.date.today()}",
            "",
            f"`{' '.join([Path(sys.executable).name, *sys.argv])}` on {platform.machine()}, "
            f"{os.cpu_count()} cores, Python {platform.python_version()}; best of {args.repeat}.",
        ]
        for split in args.splits:
            report += ["", *directions_table(obs, lower, upper, split, counts, args.repeat, args.soft)]
        publish(report, not args.no_append)
        return
    M = len(BayesianDynamicField(lower, upper, PARIS_SPACING_M, PARIS_GAMMA).hinges)
    report = [
        f"## Core benchmark, {datetime.date.today()}",
        "",
        f"`{' '.join([Path(sys.executable).name, *sys.argv])}` on {platform.machine()}, "
        f"{os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}.",
        f"Paris sample: {len(obs)} points within 40 km and below 6,000 m. Grid spacing "
        f"{PARIS_SPACING_M.tolist()} m, gamma = 1/spacing^2, M = {M} hinges (picked by hand "
        "after an unweighted flight-grouped comparison of 3 spacings x 3 gammas; with --cv, the "
        "weighted comparison follows the flight split). Track weights: each flight weighs 1 per grid cell it "
        "crosses (`bdf.ingest.track_weights`). Train = statistics + factorisation(s) + variance "
        "precompute; query = mean and std of the whole test set.",
    ]
    for split in args.splits:
        test = ingest.train_test_split(obs, by=split, test_fraction=0.2, seed=0)
        Xtr, Vtr, Xte, Vte = obs.X[~test], obs.V[~test], obs.X[test], obs.V[test]
        rows = []
        weight = obs.subset(~test).track_weights(1 / np.asarray(PARIS_SPACING_M) ** 2)
        field, tr, q, mean, std = run_bdf(lower, upper, Xtr, Vtr, Xte, "auto", "auto", args.repeat, weight)
        rows.append(
            score(
                "**bdf, auto, track weights**",
                Vte,
                Vtr,
                mean,
                std,
                tr,
                q,
                f"noise std {np.round(1 / np.sqrt(field.beta_), 1).tolist()} m/s",
            )
        )
        local_field, tr, q, mean, std = run_bdf(
            lower,
            upper,
            Xtr,
            Vtr,
            Xte,
            "auto",
            "auto",
            args.repeat,
            weight,
            noise_spacing=PARIS_NOISE_SPACING_M,
        )
        rows.append(
            score(
                f"**bdf, auto, track weights, local noise {PARIS_NOISE_SPACING_M.tolist()} m**",
                Vte,
                Vtr,
                mean,
                std,
                tr,
                q,
                "mean as above",
            )
        )
        coarse = obs.subset(~test).track_weights(1 / np.asarray(COARSE_SPACING_M) ** 2)
        coarse_field, tr, q, mean, std = run_bdf(
            lower, upper, Xtr, Vtr, Xte, "auto", "auto", args.repeat, coarse, COARSE_SPACING_M
        )
        rows.append(
            score(
                f"bdf, auto, track weights, 5 km grid (M = {len(coarse_field.hinges)})",
                Vte,
                Vtr,
                mean,
                std,
                tr,
                q,
            )
        )
        _, tr, q, mean, std = run_bdf(lower, upper, Xtr, Vtr, Xte, "auto", "auto", args.repeat)
        rows.append(score("bdf, auto, unweighted", Vte, Vtr, mean, std, tr, q))
        _, tr_fixed, q_fixed, mean, std = run_bdf(
            lower, upper, Xtr, Vtr, Xte, PAPER_ALPHA, PAPER_BETA, args.repeat
        )
        rows.append(score("bdf, alpha=1e-2 beta=1e2 (paper's)", Vte, Vtr, mean, std, tr_fixed, q_fixed))
        ours_fixed_rmse = rows[-1]["RMSE"]
        if not args.skip_reference:
            for dtype in (np.float32, np.float64):
                tr, q, mean, std, min_eig = paper_reference(field.hinges, Xtr, Vtr, Xte, dtype)
                rows.append(
                    score(
                        f"paper's algorithm, {np.dtype(dtype).name}",
                        Vte,
                        Vtr,
                        mean,
                        std,
                        tr,
                        q,
                        f"{tr / tr_fixed:.0f}x our train time; min eig of precision {min_eig:.2g}",
                    )
                )
        if args.gp_points:
            tr, q, mean, std = exact_gp(Xtr, Vtr, Xte, args.gp_points)
            rows.append(score(f"exact GP (scikit-learn), {args.gp_points} pts", Vte, Vtr, mean, std, tr, q))
        if importlib.util.find_spec("gpytorch") is None:
            print("sparse GP skipped: pip install -e '.[gp]' (torch 2.13.0 CPU, gpytorch)", flush=True)
        elif split == "flight":  # minutes per split: only where prediction away from tracks is tested
            tr, q, mean, std = sparse_gp(Xtr, Vtr, Xte, args.inducing, args.sgpr_steps)
            name = f"sparse GP (GPyTorch SGPR), {args.inducing} inducing, {args.sgpr_steps} Adam steps"
            rows.append(score(name, Vte, Vtr, mean, std, tr, q, "all training points"))
        title = "random 20% of points" if split == "point" else "20% of whole flights held out"
        report += ["", f"### Split: {title} (train {len(Xtr)}, test {len(Xte)})", "", table(rows)]
        if args.cv and split == "flight":
            report += [
                "",
                "Track-weighted, flight-grouped 5-fold cross-validation on this training set "
                "(`bdf.crossval.cross_validate`, alpha = beta = auto):",
                "",
                cv_table(weighted_cv(obs.subset(~test), lower, upper)),
                "",
                "Local noise on the 4 km grid, same folds and weights:",
                "",
                noise_cv_table(noise_cv(obs.subset(~test), lower, upper)),
            ]
        if not args.skip_reference:
            ref64 = next(r for r in rows if r["method"].endswith("float64"))
            report.append(
                f"\nbdf (paper's alpha, beta) RMSE vs paper's algorithm float64: "
                f"{100 * (ours_fixed_rmse / ref64['RMSE'] - 1):+.3f}%"
            )
        print("\n".join(report[-3:]), flush=True)

    q100k = obs.X[np.random.default_rng(0).integers(0, len(obs), 100_000)]
    q_s, _ = best_of(args.repeat, lambda: field.predict(q100k, return_std=True))
    q_local_s, _ = best_of(args.repeat, lambda: local_field.predict(q100k, return_std=True))
    mean_ms, std_ms = microscopic()
    report += [
        "",
        f"Query of 100,000 points (mean and std): {q_s:.3f} s; with local noise {q_local_s:.3f} s.",
        f"Microscopic, 300-point radar scan, M = 500: partial_fit + mean at 1,000 points {mean_ms:.2f} ms; "
        f"partial_fit + mean and std {std_ms:.2f} ms (medians of 200).",
        "",
    ]
    publish(report, not args.no_append)


if __name__ == "__main__":
    main()
