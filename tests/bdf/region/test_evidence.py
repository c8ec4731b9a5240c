import numpy as np
import pytest

from bdf import Evidence
from bdf.region.evidence import increments, region_total
from bdf.region.spec import RegionSpec
from bdf.sparse import stencil_on
from tests.bdf.region.conftest import LOCAL, SMALL


def test_each_observation_is_counted_once_and_the_tiles_sum_to_the_region(small):
    spec, X, V = small
    w = np.random.default_rng(1).uniform(0.5, 2.0, len(X))
    tile_increments = increments(spec, X, V, sample_weight=w)
    assert sum(i.points for i in tile_increments.values()) == len(X)
    assert sum(i.evidence.count for i in tile_increments.values()) == pytest.approx(w.sum(), rel=1e-12)
    region = region_total(spec, {k: i.evidence for k, i in tile_increments.items()})
    assert len(region.classes) == spec.model_sectors.classes
    total = region.total()  # every class's
    direct = Evidence.from_points(spec.grid, spec.kernel, X, V, sample_weight=w)
    for name in ("density", "proj", "mass", "v_sum", "v_sq"):
        got, want = getattr(total, name), getattr(direct, name)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())


def test_stored_blob_round_trips_with_and_without_noisy_points_and_local_noise(small):
    spec, X, V = small
    local = RegionSpec.model_validate({**SMALL, **LOCAL})
    grid, kernel = spec.tile_grid((0, 0, 0)), spec.kernel
    stencil, lattice = stencil_on(grid, kernel), local.tile_noise_lattice((0, 0, 0))
    noise = np.zeros((50, 3))
    noise[:10] = 4.0  # ten noisy-input points: a Gram band
    for evidence, with_lattice in (
        (Evidence.from_points(grid, kernel, X[:50], V[:50]), None),
        (Evidence.from_points(grid, kernel, X[:50], V[:50], noise), None),
        (Evidence.from_points(grid, kernel, X[:50], V[:50], noise_lattice=lattice), lattice),
        (Evidence.from_points(grid, kernel, X[:50], V[:50], noise, noise_lattice=lattice), lattice),
    ):
        back = Evidence.from_bytes(evidence.to_bytes(), grid, stencil, with_lattice)
        assert back.to_arrays().keys() == evidence.to_arrays().keys()
        for name, value in evidence.to_arrays().items():
            np.testing.assert_array_equal(back.to_arrays()[name], value)
        with pytest.raises(ValueError, match="does not fit a grid"):
            Evidence.from_bytes(evidence.to_bytes()[:-8], grid, stencil, with_lattice)
        with pytest.raises(ValueError, match="does not fit a grid"):  # read with the other spec
            Evidence.from_bytes(evidence.to_bytes(), grid, stencil, lattice if with_lattice is None else None)
