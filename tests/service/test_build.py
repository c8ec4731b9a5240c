"""Dask builds: many files, summed on the workers, one exactly-once upload."""

import itertools
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from distributed import Client, LocalCluster

from bdf.tiles import RegionSpec
from service.build import build
from service.maps import RegionMaps
from service.store import open_store
from tests.service.test_api import enu_columns
from tests.service.test_store import SPEC, assert_evidence_equal, data


def write(path, X, V, weight=None):
    columns = enu_columns(X, V)
    if weight is not None:
        columns["sample_weight"] = weight
    table = pa.table(columns)
    if path.suffix == ".parquet":
        pq.write_table(table, path)
    else:
        with pa.ipc.new_stream(path, table.schema) as writer:
            writer.write_table(table)
    return path


@pytest.fixture(scope="module")
def client():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False) as cluster, Client(cluster) as c:
        yield c


def test_build_equals_one_upload_of_all_files_and_replays(store, spec, client, tmp_path):
    X, V = data(0, n=1200)
    X[5, 0], X[17] = np.nan, [900.0, 10.0, 10.0]  # one non-finite row, one outside
    weight = np.random.default_rng(1).uniform(0.2, 2.0, len(X))
    cuts = [0, 300, 500, 900, 1100, 1200]
    paths = [
        write(tmp_path / f"part{i}.{'arrow' if i == 2 else 'parquet'}", X[a:b], V[a:b], weight[a:b])
        for i, (a, b) in enumerate(itertools.pairwise(cuts))
    ]
    store.create_region(spec.model_copy(update={"name": "batch"}))
    expected = RegionMaps(store).upload("batch", "all", X, V, sample_weight=weight)

    result = build(store, "town", paths, client, progress=False)
    assert {k: result[k] for k in ("accepted", "rejected", "region_version", "replayed")} == {
        "accepted": 1198,
        "rejected": {"non_finite": 1, "outside_region": 1},
        "region_version": 1,
        "replayed": False,
    }
    assert result["tiles_updated"] == expected["tiles_updated"]
    built = store.snapshot("town")
    assert_evidence_equal(built.evidence, store.snapshot("batch").evidence, rtol=1e-9)
    assert built.region.observations == 1198

    again = build(store, "town", paths, client, progress=False)
    assert again["replayed"] and store.region("town").version == 1
    added = build(store, "town", paths[:1], client, replace=False, progress=False)
    assert (
        added["region_version"] == 2 and store.region("town").observations == 1198 + 298
    )  # part0 holds both bad rows
    refit = build(store, "town", paths, client, progress=False, upload_id="refit")
    assert refit["region_version"] == 3 and store.region("town").observations == 1198


def test_a_bad_file_fails_the_build_and_stores_nothing(store, spec, client, tmp_path):
    X, V = data(2, n=100)
    good = write(tmp_path / "good.parquet", X, V)
    pq.write_table(pa.table({"x": X[:, 0], "y": X[:, 1], "z": X[:, 2]}), tmp_path / "novel.parquet")
    (tmp_path / "notes.csv").write_text("x,y\n")
    for paths, message in (
        ([good, tmp_path / "novel.parquet"], "novel.parquet: the table lacks the velocity columns"),
        ([good, tmp_path / "notes.csv"], "notes.csv: a build reads .parquet or .arrow files"),
        ([good, tmp_path / "missing.parquet"], "missing.parquet: no such file"),
        ([], "at least one"),
    ):
        with pytest.raises(ValueError, match=message):
            build(store, "town", paths, client, progress=False)
    assert store.region("town").version == 0 and store.snapshot("town").tiles == {}


def test_bdf_build_command_on_a_process_cluster(tmp_path):
    """``bdf build`` starts a local cluster of worker processes when no scheduler is given."""
    url = f"sqlite:///{tmp_path / 'data'}"
    store = open_store(url)
    spec = store.create_region(RegionSpec.model_validate(SPEC)).spec
    X, V = data(3, n=400)
    paths = [write(tmp_path / f"p{i}.parquet", X[i::2], V[i::2]) for i in range(2)]
    cmd = [
        sys.executable,
        "-m",
        "clients.cli",
        "build",
        "--region",
        "town",
        "--store-url",
        url,
        "--workers",
        "2",
    ]
    run = subprocess.run([*cmd, *map(str, paths)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "400 accepted" in run.stdout and "version 1" in run.stdout
    expected = {k: i.evidence for k, i in spec.increments(X, V).items()}
    assert_evidence_equal(store.snapshot("town").evidence, expected, rtol=1e-9)
    run = subprocess.run(
        [*cmd, str(tmp_path / "nothing.parquet")], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 2 and run.stderr.strip().endswith("nothing.parquet: no such file")
    store.close()
