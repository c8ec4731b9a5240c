import gzip
import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from bdf import ingest
from bdf.frames import ENUFrame

PARIS = ENUFrame(48.84, 2.51, 0.0)


def test_enu_round_trip_and_geometry():
    lat = 48.84 + np.array([0.0, 0.1, -0.3])
    lon = 2.51 + np.array([0.0, 0.2, 0.4])
    alt = np.array([0.0, 1000.0, 5000.0])
    enu = PARIS.to_enu(lat, lon, alt)
    np.testing.assert_allclose(enu[0], 0.0, atol=1e-6)
    back = PARIS.to_geodetic(enu)
    np.testing.assert_allclose(back[:, :2], np.stack([lat, lon], 1), atol=1e-10)
    np.testing.assert_allclose(back[:, 2], alt, atol=1e-6)
    # 0.1 deg of latitude north is ~11.1 km north, with the earth curving ~10 m down
    north = PARIS.to_enu(48.94, 2.51, 0.0)
    assert north[0] == pytest.approx(0.0, abs=1e-6)
    assert north[1] == pytest.approx(11_121, rel=1e-3)
    assert -12 < north[2] < -8


def test_velocity_rotation():
    v = np.array([[100.0, 50.0, -5.0]])
    np.testing.assert_allclose(PARIS.rotate_velocity([48.84], [2.51], v), v, atol=1e-12)
    far = PARIS.rotate_velocity([48.84], [3.51], v)  # 1 degree east: axes turn by ~0.75 deg
    assert np.linalg.norm(far) == pytest.approx(np.linalg.norm(v), rel=1e-12)
    angle = np.degrees(np.arctan2(far[0, 1], far[0, 0]) - np.arctan2(50, 100))
    assert angle == pytest.approx(np.sin(np.radians(48.84)) * 1.0, rel=0.02)


def test_enu_origin_is_validated():
    with pytest.raises(ValueError, match="origin out of range"):
        ENUFrame(95.0, 0.0)


ROWS = [
    # timestamp (ms), icao24, callsign, lat, lon, altitude ft, gs kt, track, vrate ft/min, onground
    (1633608773000, "abc123", "AF1", 48.84, 2.51, 10000.0, 100.0, 90.0, 600.0, False),
    (1633608774000, "abc123", "AF1", 48.85, 2.51, 10000.0, 200.0, 0.0, -1200.0, False),
    (1633608775000, "def456", "BA2", 48.86, 2.52, 0.0, 10.0, 0.0, 0.0, True),
    (1633608776000, "def456", "BA2", 48.87, 2.53, None, 300.0, 180.0, 0.0, False),
]
NAMES = [
    "timestamp",
    "icao24",
    "callsign",
    "latitude",
    "longitude",
    "altitude",
    "groundspeed",
    "track",
    "vertical_rate",
    "onground",
]


def _check(obs):
    assert len(obs) == 2
    assert obs.dropped == {"on_ground": 1, "incomplete": 1}
    np.testing.assert_allclose(obs.V[0], [100 * 1852 / 3600, 0.0, 600 * 0.3048 / 60], atol=1e-3)
    np.testing.assert_allclose(obs.V[1], [0.0, 200 * 1852 / 3600, -1200 * 0.3048 / 60], atol=0.05)
    assert obs.X[0, 2] == pytest.approx(10000 * 0.3048, abs=1e-3)
    np.testing.assert_array_equal(obs.time, [1633608773.0, 1633608774.0])
    assert obs.flight[0] == obs.flight[1]


def test_adsb_from_json_gz_csv_and_parquet(tmp_path):
    records = [dict(zip(NAMES, r, strict=True)) for r in ROWS]
    with gzip.open(tmp_path / "s.json.gz", "wt") as fh:
        json.dump(records, fh)
    _check(ingest.read_adsb(tmp_path / "s.json.gz", PARIS))
    table = pa.table({n: [r[i] for r in ROWS] for i, n in enumerate(NAMES)})
    pq.write_table(table, tmp_path / "s.parquet")
    _check(ingest.read_adsb(tmp_path / "s.parquet", PARIS))
    lines = [",".join(NAMES)] + [",".join("" if v is None else str(v) for v in r) for r in ROWS]
    (tmp_path / "s.csv").write_text("\n".join(lines))
    _check(ingest.read_adsb(tmp_path / "s.csv", PARIS))


def test_adsb_from_opensky_state_vector_files(tmp_path):
    """OpenSky's own files: seconds, metres, m/s, the geometric height (else the barometric)."""
    si = {
        "time": [r[0] / 1000 for r in ROWS],
        "icao24": [r[1] for r in ROWS],
        "callsign": [r[2] for r in ROWS],
        "lat": [r[3] for r in ROWS],
        "lon": [r[4] for r in ROWS],
        "baroaltitude": [None if r[5] is None else r[5] * 0.3048 for r in ROWS],
        "velocity": [r[6] * 1852 / 3600 for r in ROWS],
        "heading": [r[7] for r in ROWS],
        "vertrate": [r[8] * 0.3048 / 60 for r in ROWS],
        "onground": [r[9] for r in ROWS],
    }
    pq.write_table(pa.table(si), tmp_path / "states.parquet")
    _check(ingest.read_adsb(tmp_path / "states.parquet", PARIS))
    si["geoaltitude"] = [None, 3100.0, 0.0, 3000.0]
    obs = ingest.adsb_observations({k: np.array(v, dtype=object) for k, v in si.items()}, PARIS)
    assert obs.dropped == {"on_ground": 1, "incomplete": 1}  # row 0 has no geometric height
    np.testing.assert_allclose(obs.X, PARIS.to_enu([48.85, 48.87], [2.51, 2.53], [3100.0, 3000.0]), atol=1e-6)


def test_adsb_missing_column_and_unknown_format(tmp_path):
    (tmp_path / "s.csv").write_text("latitude,longitude\n1,2\n")
    with pytest.raises(ValueError, match="ADS-B state vectors need the columns icao24 and latitude"):
        ingest.read_adsb(tmp_path / "s.csv", PARIS)
    with pytest.raises(ValueError, match="unknown format"):
        ingest.read_adsb(tmp_path / "s.xlsx", PARIS)


def test_radar_csv(tmp_path):
    (tmp_path / "r.csv").write_text("x,y,z,vx,vy,vz,t\n1,2,3,4,5,6,0.5\n1,2,,4,5,6,0.6\n")
    obs = ingest.read_radar(tmp_path / "r.csv")
    np.testing.assert_array_equal(obs.X, [[1, 2, 3]])
    np.testing.assert_array_equal(obs.V, [[4, 5, 6]])
    assert obs.dropped == {"incomplete": 1}
    np.testing.assert_array_equal(obs.flight, [-1])  # no track id: a track of its own
    (tmp_path / "s.csv").write_text("x,y,z,vx,vy,vz,t,track\n1,2,3,4,5,6,0.5,T9\n1,2,3,4,5,6,0.6,T2\n")
    np.testing.assert_array_equal(ingest.read_radar(tmp_path / "s.csv").flight, [1, 0])
