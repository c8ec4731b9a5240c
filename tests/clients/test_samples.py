import subprocess

import numpy as np
import pytest

from clients import samples


def test_an_unknown_sample_is_refused_and_a_cached_one_is_not_downloaded_again(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="unknown sample 'tokyo'; available: \\['paris'\\]"):
        samples.fetch_sample("tokyo", tmp_path)
    cached = tmp_path / "paris-quickstart.json.gz"
    cached.write_bytes(b"cached")

    def no_download(*args, **kwargs):
        raise AssertionError("pip ran for a sample already in the cache")

    monkeypatch.setattr(subprocess, "run", no_download)
    assert samples.fetch_sample("paris", tmp_path) == cached
    assert cached.read_bytes() == b"cached"


def test_the_paris_regions_hold_the_box_on_the_samples_origin():
    """One field over the box (1 km below it for the earth's curvature), 10 km tiles over the
    whole altitude band, gamma = 1 / spacing^2; the demo's on its own lattice and cutoff."""
    lower, upper = np.array([-20_000.0, -20_000.0, 0.0]), np.array([20_000.0, 20_000.0, 6_000.0])
    spec = samples.paris_region(lower, upper)
    assert (spec.origin.lat, spec.origin.lon) == (48.84, 2.51)
    np.testing.assert_array_equal(spec.lower, [-20_000.0, -20_000.0, -1_000.0])
    assert spec.tile_counts == (4, 4, 1)
    np.testing.assert_allclose(spec.gamma, 1.0 / samples.PARIS_SPACING_M**2)
    demo = samples.paris_demo_region(lower, upper, directions=8)
    assert demo.spacing_m == samples.PARIS_REGION_SPACING_M.tolist() and demo.directions == 8
    assert demo.cutoff == samples.PARIS_REGION_CUTOFF
