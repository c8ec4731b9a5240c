import numpy as np
import pytest

from bdf.region.spec import RegionSpec, key_str, parse_key
from tests.bdf.region.conftest import PARIS


def test_spec_json_is_the_service_body():
    spec = RegionSpec.model_validate(PARIS)
    assert spec.model_dump(mode="json") == {
        **PARIS,
        "bounds_m": {"min": [-40000.0, -40000.0, 0.0], "max": [40000.0, 40000.0, 6000.0]},
        "tile_size_m": [10000.0, 10000.0, 6000.0],
        "spacing_m": [4000.0, 4000.0, 1000.0],
        "noise_spacing_m": None,  # the global noise
        "noise_prior": 0.1,
        "cutoff": 1e-12,
        "directions": "auto",  # chosen by its fits
        "model_directions": 16,  # until the first fit chooses
        "directions_scores": None,  # written by the fits of a region of "auto" directions
        "slow_mps": 5.0,
        "track_interval_s": 1.0,
        "envelope": {  # aircraft
            "max_horizontal_speed_mps": 400.0,
            "max_vertical_speed_mps": 100.0,
            "max_input_noise_std_m": 1000.0,
            "min_sample_weight": 1e-06,
            "max_sample_weight": 1000.0,
        },
    }
    assert spec.tile_counts == (8, 8, 1)
    assert spec.grid.shape == (21, 21, 7)  # the Paris core lattice, 3,087 hinges
    grid = spec.tile_grid((3, 3, 0))
    # core [-10000, 0] grown by the kernel's reach at the cutoff (7.4 km), on the 4 km lattice
    np.testing.assert_allclose(grid.origin, [-16000, -16000, 0])
    assert grid.shape == (6, 6, 7)
    assert parse_key(key_str((3, 1, 0))) == (3, 1, 0)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"name": "Paris!"}, "pattern"),
        ({"bounds_m": {"min": [0, 0, 0], "max": [10, -1, 10]}}, "must exceed"),
        ({"spacing_m": [100, 100, 100]}, "hinges"),  # 801 x 801 x 61 in the region
        ({"gamma": [1, -1, 1]}, "greater than 0"),
        ({"alpha": "aut"}, "alpha"),
        ({"tile_size_m": [100, 100, 100]}, "tiles"),
        ({"origin": {"lat": 91, "lon": 0}}, "lat"),
        ({"extra": 1}, "extra"),
        ({"cutoff": 1}, "less than 1"),
        ({"directions": 33}, "less than or equal to 32"),
        ({"directions": 0}, "greater than or equal to 1"),
        ({"directions": 8, "model_directions": 16}, "must equal directions 8"),
        ({"model_directions": 33}, "less than or equal to 32"),
        ({"overlap_m": [1000, 1000, 0]}, "extra"),  # tiles no longer overlap
        ({"noise_spacing_m": [100, 100, 100]}, "noise lattice would have"),
        ({"noise_spacing_m": [1000, 1000, 100], "noise_prior": 0}, "greater than 0"),
    ],
)
def test_spec_rejects_bad_values(change, message):
    with pytest.raises(ValueError, match=message):
        RegionSpec.model_validate({**PARIS, **change})


@pytest.mark.parametrize(
    ("given", "directions", "model"),
    [
        ({}, "auto", 16),
        ({"directions": 1}, 1, 8),
        ({"model_directions": 1}, 1, 1),
        ({"model_directions": 4}, 1, 4),
        ({"directions": 16}, 16, 16),
    ],
)
def test_a_new_region_chooses_its_sectors_and_one_of_one_class_answers_from_eight_unless_told(
    given, directions, model
):
    """The model's sectors are written out, so a stored spec names what its evidence holds;
    a spec naming only its model's sectors is of one class, as before "auto" was the default."""
    spec = RegionSpec.model_validate({**PARIS, **given})
    assert spec.directions == directions
    assert spec.model_directions == model and spec.model_sectors.directions == model
    assert spec.sectors.directions == (model if directions == "auto" else directions)
    assert spec.posteriors == (1 if model == 1 else 2 + model)
    assert RegionSpec.model_validate(spec.model_dump(mode="json")) == spec
