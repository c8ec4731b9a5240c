"""A region's heading resolution chosen by its data (bdf.region.resolution)."""

import numpy as np
import pytest

from bdf import hyperparameters, metrics
from bdf.region.evidence import accepted_increments, checked_rows, region_total
from bdf.region.map import RegionMap, compute_posterior
from bdf.region.resolution import _start_from, choose_directions
from bdf.region.spec import AUTO_FIRST_DIRECTIONS, RegionSpec
from bdf.sectors import AUTO_DIRECTIONS

CROSSING = {
    "name": "crossing",
    "origin": {"lat": 48.0, "lon": 2.0},
    "bounds_m": {"min": [-8000, -8000, 0], "max": [8000, 8000, 1000]},
    "tile_size_m": [8000, 8000, 1000],
    "spacing_m": [2000, 2000, 1000],
    "gamma": [2.5e-7, 2.5e-7, 1e-6],
    "directions": "auto",
}
#: every flow flies this fast (m/s), its rows 1 s apart
SPEED_MPS = 60.0
HEADINGS_DEG = np.arange(12) * 30.0


def crossing_flows(offsets_m, seed):
    """Straight 1 Hz tracks through the region at 12 evenly spread headings, each flow a
    track per cross-track offset, at 500 m: rows with their track and time."""
    rng = np.random.default_rng(seed)
    X, V, track, t = [], [], [], []
    for h in np.radians(HEADINGS_DEG):
        along, across = np.array([np.sin(h), np.cos(h)]), np.array([np.cos(h), -np.sin(h)])
        for offset in offsets_m:
            s = np.arange(-7500.0, 7500.0, SPEED_MPS)
            xy = s[:, None] * along + offset * across
            X.append(np.column_stack([xy, np.full(len(s), 500.0)]))
            V.append(np.column_stack([np.tile(SPEED_MPS * along, (len(s), 1)), np.zeros(len(s))]))
            track.append(np.full(len(s), len(track)))
            t.append(np.arange(len(s), dtype=float))
    V = np.concatenate(V) + rng.normal(0.0, 1.0, (sum(map(len, X)), 3))
    return np.concatenate(X), V, np.concatenate(track), np.concatenate(t)


def conditional_rmse(rmap: RegionMap, X, V) -> float:
    """RMSE of the mode of each row's own heading."""
    heading = np.degrees(np.arctan2(V[:, 0], V[:, 1]))
    return float(metrics.rmse(V, rmap.predict(X, heading)[0]))


def test_auto_picks_sectors_fine_enough_for_twelve_crossing_flows_and_predicts_their_headings():
    spec = RegionSpec.model_validate(CROSSING)
    assert spec.model_directions == AUTO_FIRST_DIRECTIONS  # until a fit chooses
    X, V, track, t = crossing_flows(np.arange(-3500, 3501, 1000), seed=0)  # 8 tracks a flow
    choice = choose_directions(spec, checked_rows(X, V, track=track, time=t))
    chosen = choice.spec.model_directions
    assert chosen >= 12
    scores = {s.directions: s for s in choice.spec.directions_scores}
    assert sorted(scores) == list(AUTO_DIRECTIONS) and [
        s.directions for s in scores.values() if s.chosen
    ] == [chosen]
    assert choice.spec.sectors.directions == chosen and choice.spec.directions == "auto"
    # the chosen map is the map of all the rows at that count, as a fit stores it
    increments, _ = accepted_increments(choice.spec, X, V, track=track, time=t)
    assert sorted(increments) == sorted(choice.increments)
    evidence = region_total(choice.spec, {k: i.evidence for k, i in increments.items()})
    assert choice.posterior.total.weights == pytest.approx(
        compute_posterior(choice.spec, evidence).total.weights, abs=1e-9
    )
    # held-out tracks between those seen: the mode of their heading, against 8 sectors
    Xt, Vt, _, _ = crossing_flows(np.arange(-3000, 3001, 1000), seed=1)
    eight = spec.with_directions(8)
    increments, _ = accepted_increments(eight, X, V, track=track, time=t)
    rmap8 = RegionMap(
        eight, compute_posterior(eight, region_total(eight, {k: i.evidence for k, i in increments.items()}))
    )
    auto, coarse = (
        conditional_rmse(RegionMap(choice.spec, choice.posterior), Xt, Vt),
        conditional_rmse(rmap8, Xt, Vt),
    )
    assert auto <= coarse * 2 / 3, (auto, coarse)


def test_each_count_searches_from_the_optimum_of_the_one_before_to_the_same_map_in_fewer_solves(
    monkeypatch,
):
    spec = RegionSpec.model_validate(CROSSING)
    X, V, track, t = crossing_flows(np.arange(-3500, 3501, 1000), seed=0)
    solves = []
    solve = hyperparameters.solve
    monkeypatch.setattr(hyperparameters, "solve", lambda *a: solves.append(1) or solve(*a))

    def fitted(directions, start=None):
        candidate = spec.with_directions(directions)
        increments, _ = accepted_increments(candidate, X, V, track=track, time=t)
        evidence = region_total(candidate, {k: i.evidence for k, i in increments.items()})
        solves.clear()
        post = compute_posterior(candidate, evidence, start, stored=False)
        return post, len(solves)

    sixteen, _ = fitted(16)
    start = _start_from(sixteen.next_start, 24)
    assert start.shape == (26, 3)  # the map with one class, 24 sectors, the slow class
    # sector k of 24 starts at the 16-sector row holding its centre (15 k degrees)
    np.testing.assert_array_equal(
        start[1:-1], sixteen.next_start[1 + np.round(np.arange(24) * 15 / 22.5).astype(int) % 16]
    )
    fresh, from_scratch = fitted(24)
    started, from_start = fitted(24, start)
    assert from_start < from_scratch, (from_start, from_scratch)
    np.testing.assert_allclose(started.alpha, fresh.alpha, rtol=1e-5)
    np.testing.assert_allclose(started.beta, fresh.beta, rtol=1e-5)
    assert _start_from(None, 8) is None


def test_too_few_tracks_keep_the_model_in_force():
    spec = RegionSpec.model_validate(CROSSING)
    X, V, track, t = crossing_flows([0], seed=0)
    keep = track < 2  # two tracks: no three folds
    choice = choose_directions(spec, checked_rows(X[keep], V[keep], track=track[keep], time=t[keep]))
    assert choice.spec.model_directions == AUTO_FIRST_DIRECTIONS and choice.spec.directions_scores is None
    assert choice.summary["accepted"] == keep.sum()


def test_a_spec_of_auto_directions_answers_its_models_sectors_and_refuses_what_it_cannot_be():
    spec = RegionSpec.model_validate(CROSSING)
    assert spec.sectors.directions == AUTO_FIRST_DIRECTIONS and not spec.one_class
    assert spec.with_directions(24).sectors.directions == 24
    with pytest.raises(ValueError, match="model_directions > 1"):
        RegionSpec.model_validate({**CROSSING, "model_directions": 1})
    with pytest.raises(ValueError, match="written by the fit"):
        RegionSpec.model_validate(
            {
                **CROSSING,
                "directions": 8,
                "directions_scores": [
                    {
                        "directions": 8,
                        "mixture_msll": -1.0,
                        "mixture_msll_se": 0.1,
                        "msll": -1.0,
                        "conditional_rmse_mps": 1.0,
                        "chosen": True,
                    }
                ],
            }
        )
