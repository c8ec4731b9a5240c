"""Why a map of one class is implausible, and what the model changes tried do about it.

The Paris flight split's raw rows with their track columns (the service's weights), the
demo's lattice, one class. Over the box (``bench_tracks.plausibility``'s grid: 1 km, every
500 m) a map of one class reaches 2.8 times the fastest traffic near its altitude, always
where no data lies (``known`` false): where arrivals and departures fly opposite ways a few
hundred metres apart in altitude, one smooth field fits them with large alternating weights
between two hinge layers, and those swing far past the data beside them. Variants, each
judged on the held-out flights and over the box, with its log evidence:

* ``served``: the evidence maximum (what the service serves);
* ``local prior``: a prior mean at each hinge, the class's mean velocity near it in its
  layer, as the directional modes have (``bdf.posterior._local_prior``);
* ``roughness prior x rho``: prior precision ``alpha (I + rho L)``, ``L`` the lattice's
  graph Laplacian (neighbouring hinges' weights pulled together), ratio at its evidence
  maximum (a golden-section search on the exact log determinants);
* ``ratio x e^k``: alpha / beta raised above the maximum (beta at its optimum for that
  ratio): a floor on the ratio, as the issue suggests.

    python bench/bench_one_class.py [--publish]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from bench_core import publish, rows_table
from bench_tracks import plausibility, split

from bdf import metrics, sparse
from bdf.hyperparameters import solve
from bdf.posterior import Posterior, _local_prior
from bdf.region.evidence import accepted_increments, region_total
from bdf.region.map import RegionMap, region_field, speed_bound
from clients import samples

#: the golden-section search of the roughness prior's ratio: ln(alpha / beta) bracket, steps
ROUGH_BRACKET, ROUGH_STEPS = (-6.0, 4.0), 14


def laplacian_band(stencil: sparse.Stencil) -> np.ndarray:
    """The lattice's graph Laplacian (6 neighbours) as a band on ``stencil``."""
    band = np.zeros((len(stencil.offsets), stencil.size))
    offsets = [tuple(o) for o in stencil.offsets]
    for axis in range(3):
        k = offsets.index(tuple(np.eye(3, dtype=int)[axis]))
        pair = np.zeros(stencil.shape)
        pair[stencil.valid(k)] = 1.0
        band[k] -= pair.ravel()
        degree = pair.copy()
        degree += np.roll(pair, 1, axis=axis)  # each pair's second hinge, one step on
        band[0] += degree.ravel()
    return band


def roughness_mean(post: Posterior, evidence, rho: float) -> tuple[np.ndarray, float]:
    """The posterior mean weights (M, 3) under the prior precision ``alpha (I + rho L)`` at the
    ratio of greatest evidence (beta at its optimum per component), and that evidence."""
    st = post.stencil
    gram, lap = evidence.gram_band(st), laplacian_band(st)
    logdet_prior = st.factor_of(rho * lap, 1.0).logdet()
    M, N = st.size, evidence.count

    def at(x):
        lam = np.exp(x)
        factor = st.factor_of(gram + lam * rho * lap, lam)
        weights = factor.solve(evidence.proj)
        residual = evidence.v_sq - np.einsum("mc,mc->c", evidence.proj, weights)
        beta = N / residual
        value = (
            0.5 * M * np.log(lam * beta)
            + 0.5 * logdet_prior
            + 0.5 * N * np.log(beta)
            - 0.5 * beta * residual
            - 0.5 * (M * np.log(beta) + factor.logdet())
            - 0.5 * N * np.log(2 * np.pi)
        )
        return float(value.sum()), weights

    lo, hi = ROUGH_BRACKET
    golden = (np.sqrt(5) - 1) / 2
    for _ in range(ROUGH_STEPS):
        a, b = hi - golden * (hi - lo), lo + golden * (hi - lo)
        if at(a)[0] > at(b)[0]:
            hi = b
        else:
            lo = a
    value, weights = at((lo + hi) / 2)
    return weights, value


def main():
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--publish", action="store_true", help="append the report to bench/RESULTS.md")
    args = parser.parse_args()
    train, test, lower, upper = split()
    spec = samples.paris_demo_region(lower, upper, directions=1, model_directions=1)  # the paper's
    increments, _ = accepted_increments(spec, train.X, train.V, track=train.flight, time=train.time)
    classes = region_total(spec, {k: i.evidence for k, i in increments.items()})
    evidence = classes.total()
    grid, kernel, *_ = region_field(spec)._setup()
    mu, sd = train.V.mean(0), train.V.std(0)
    served = Posterior(grid, kernel, evidence, "auto", "auto")
    lam = float(served.alpha[0] / served.beta[0])
    rows = []

    def judge(name, post, log_evidence, with_std=True):
        post.speed_bound = speed_bound(spec, classes.speeds)  # what known() judges by
        rmap = RegionMap(spec, post)
        row = {"variant": name}
        if with_std:
            mean, std, _ = rmap.predict(test.X)
            row |= {
                "RMSE": float(metrics.rmse(test.V, mean)),
                "MSLL": float(metrics.msll(test.V, mean, std, mu, sd)),
                "cov95": float(metrics.coverage(test.V, mean, std)),
            }
        else:
            row["RMSE"] = float(metrics.rmse(test.V, post.mean(test.X)))
        judged = plausibility(spec, rmap, train)
        row |= {
            "worst ratio to bound": judged["worst ratio to bound"],
            "implausible voxels": judged["implausible voxels"],
            "implausible among known": judged["implausible among known"],
            "log evidence": log_evidence,
        }
        rows.append(row)
        print(row, flush=True)

    t0 = time.perf_counter()
    judge("served (evidence maximum)", served, float(served.log_evidence.sum()))
    local = Posterior(
        grid, kernel, evidence, "auto", "auto", prior_weights=_local_prior(evidence, grid, kernel.gamma)
    )
    judge("local prior", local, float(local.log_evidence.sum()))
    for rho in (1.0,):
        rough = Posterior(grid, kernel, evidence, served.alpha, served.beta)
        rough.weights, value = roughness_mean(served, evidence, rho)
        judge(f"roughness prior x {rho:g} (mean only)", rough, value, with_std=False)
    for k in (1.5, 2.5, 3.5):
        residual = solve(
            served.stencil, evidence.gram_band(served.stencil), evidence.proj, evidence.v_sq, lam * np.exp(k)
        ).residual
        beta = evidence.count / residual
        raised = Posterior(grid, kernel, evidence, lam * np.exp(k) * beta, beta)
        judge(f"ratio x e^{k:g}", raised, float(raised.log_evidence.sum()))
    command = "python bench/bench_one_class.py"
    publish(
        [
            f"\n## One class: what the model changes tried do ({time.strftime('%Y-%m-%d')}, `{command}`)\n",
            "Paris flight split, raw rows with track and t (the service's weights), the demo's lattice, "
            f"one class; {time.perf_counter() - t0:.0f} s.",
            rows_table(rows),
        ],
        args.publish,
    )


if __name__ == "__main__":
    main()
