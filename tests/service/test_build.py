"""Dask builds: files of any size in bounded slices, summed on the workers, one exactly-once upload."""

import gzip
import itertools
import json
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from distributed import Client, LocalCluster

from bdf import ingest
from bdf.region.evidence import increments
from bdf.region.spec import RegionSpec
from service.build import ClusterLost, build, plan
from service.maps import RegionMaps
from service.store import open_store
from tests.service.test_api import enu_columns
from tests.service.test_store import NO_REJECTS, SPEC, assert_evidence_equal, data

pytestmark = pytest.mark.slow  # Dask clusters


def write(path, X, V, weight=None, rows=None, **extra):
    """``X, V`` in the format of ``path``'s suffix, in chunks of ``rows`` rows (row groups,
    record batches); ``extra`` columns after them."""
    columns = enu_columns(X, V)
    if weight is not None:
        columns["sample_weight"] = weight
    columns.update(extra)
    table = pa.table(columns)
    name = path.name
    if name.endswith(".parquet"):
        pq.write_table(table, path, row_group_size=rows)
    elif name.endswith(".arrow"):
        new = pa.ipc.new_file if "file" in name else pa.ipc.new_stream
        with new(path, table.schema) as writer:
            writer.write_table(table, max_chunksize=rows)
    else:
        lines = [",".join(columns)] + [
            ",".join(v if isinstance(v, str) else repr(float(v)) for v in row)
            for row in zip(*columns.values(), strict=True)
        ]
        text = "\n".join(lines) + "\n"
        if name.endswith(".gz"):
            with gzip.open(path, "wt") as fh:
                fh.write(text)
        else:
            path.write_text(text)
    return path


@pytest.fixture(scope="module")
def client():
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as c,
    ):
        yield c


def test_slices_of_every_format_build_what_one_upload_of_all_rows_learns(store, spec, client, tmp_path):
    X, V = data(0, n=1500)
    X[5, 0], X[17] = np.nan, [900.0, 10.0, 10.0]  # one non-finite row, one outside
    weight = np.random.default_rng(1).uniform(0.2, 2.0, len(X))
    names = ["a.parquet", "b.arrow", "c.file.arrow", "d.csv", "e.csv.gz"]
    cuts = [0, 400, 700, 1000, 1300, 1500]
    paths = [
        write(tmp_path / name, X[a:b], V[a:b], weight[a:b], rows=70)
        for name, (a, b) in zip(names, itertools.pairwise(cuts), strict=True)
    ]
    pieces = plan(paths, rows_per_task=100)
    # row groups of 70 -> runs of one; arrow rows 0-100, 100-200, ...; CSV byte ranges; gz whole
    assert [len([p for p in pieces if p.path == str(path)]) for path in paths] == [6, 3, 3, 7, 1]
    store.create_region(spec.model_copy(update={"name": "batch"}))
    expected = RegionMaps(store).upload("batch", "all", X, V, sample_weight=weight)

    result = build(store, "town", paths, client, progress=False, rows_per_task=100, batch_rows=33)
    assert {k: result[k] for k in ("accepted", "rejected", "region_version", "replayed")} == {
        "accepted": 1498,
        "rejected": {**NO_REJECTS, "non_finite": 1, "outside_region": 1},
        "region_version": 1,
        "replayed": False,
    }
    assert result["tiles_updated"] == expected["tiles_updated"]
    built = store.snapshot("town")
    assert_evidence_equal(built.evidence, store.snapshot("batch").evidence, rtol=1e-9)
    assert built.region.observations == 1498

    again = build(store, "town", paths, client, progress=False)  # other slices, same files: a replay
    assert again["replayed"] and store.region("town").version == 1
    added = build(store, "town", paths[:1], client, replace=False, progress=False)
    assert added["region_version"] == 2 and store.region("town").observations == 1498 + 398
    refit = build(store, "town", paths, client, progress=False, upload_id="refit")
    assert refit["region_version"] == 3 and store.region("town").observations == 1498


def test_tracks_cut_across_slices_and_batches_build_the_map_of_one_upload(store, spec, client, tmp_path):
    """Raw tracks with string ids in Parquet and CSV, cut across files, slices and batches:
    the build weighs them as one upload of all rows does."""
    from tests.service.test_tracks import tracks

    X, V, track, t = tracks(3)
    order = np.argsort(t, kind="stable")  # by time: every flight is cut between the files
    X, V, track, t = X[order], V[order], track[order], t[order]
    ids = np.array([f"flight-{k}" for k in track])
    half = len(X) // 2
    paths = [
        write(tmp_path / "a.parquet", X[:half], V[:half], rows=37, track=ids[:half], t=t[:half]),
        write(tmp_path / "b.csv", X[half:], V[half:], track=ids[half:].tolist(), t=t[half:]),
    ]
    store.create_region(spec.model_copy(update={"name": "batch"}))
    expected = RegionMaps(store).upload("batch", "all", X, V, track=track, time=t)
    result = build(store, "town", paths, client, progress=False, rows_per_task=50, batch_rows=23)
    assert (result["accepted"], result["untracked"]) == (len(X), 0) and "warnings" not in result
    assert result["tiles_updated"] == expected["tiles_updated"]
    assert_evidence_equal(store.snapshot("town").evidence, store.snapshot("batch").evidence, rtol=1e-9)


def test_adsb_state_vectors_build_in_the_regions_frame(store, spec, client, tmp_path):
    """traffic-schema CSV and JSON records and OpenSky-schema Parquet: converted on the
    worker, on-ground rows rejected and counted."""
    frame = spec.frame()
    X, V = data(5, n=300)
    lat, lon, alt = frame.to_geodetic(X).T
    local = np.einsum("nji,ni->nj", _rotation(frame, lat, lon), V)  # each point's own ENU axes
    speed, track = np.hypot(local[:, 0], local[:, 1]), np.degrees(np.arctan2(local[:, 0], local[:, 1])) % 360
    onground = np.arange(len(X)) % 50 == 0
    traffic = {
        "timestamp": 1.6e12 + np.arange(len(X)) * 1000.0,  # Unix milliseconds, 1 Hz
        "icao24": np.array(["abc"] * len(X)),
        "latitude": lat,
        "longitude": lon,
        "altitude": alt / ingest.FT,
        "groundspeed": speed / ingest.KT,
        "track": track,
        "vertical_rate": local[:, 2] / ingest.FT_PER_MIN,
        "onground": onground,
    }
    csv = tmp_path / "states.csv"
    csv.write_text(
        ",".join(traffic)
        + "\n"
        + "".join(
            ",".join(str(v) if isinstance(v, str | np.str_ | np.bool_) else repr(float(v)) for v in row)
            + "\n"
            for row in zip(*traffic.values(), strict=True)
        )
    )
    opensky = {"time": traffic["timestamp"] / 1000, "icao24": traffic["icao24"], "lat": lat, "lon": lon}
    opensky |= {"geoaltitude": alt, "velocity": speed, "heading": track, "vertrate": local[:, 2]}
    pq.write_table(pa.table(opensky | {"onground": onground}), tmp_path / "states.parquet", row_group_size=64)
    records = [  # traffic's own samples are JSON records (quickstart.json.gz)
        {k: v.item() if hasattr(v, "item") else v for k, v in zip(traffic, row, strict=True)}
        for row in zip(*traffic.values(), strict=True)
    ]
    with gzip.open(tmp_path / "states.json.gz", "wt") as fh:
        json.dump(records, fh)
    files = [csv, tmp_path / "states.parquet", tmp_path / "states.json.gz"]
    result = build(store, "town", files, client, progress=False, rows_per_task=64)
    keep = ~onground
    assert result["accepted"] == 3 * keep.sum() and result["untracked"] == 0
    assert result["rejected"] == {**NO_REJECTS, "on_ground": 3 * onground.sum()}
    # one track (icao24 "abc"), 1 Hz: weighed in each file alike, whatever its slices
    weight = ingest.track_weights(np.zeros(keep.sum(), int), np.arange(len(X))[keep], V[keep], spec.gamma)
    expected = increments(
        spec,
        np.concatenate([X[keep]] * 3),
        np.concatenate([V[keep]] * 3),
        sample_weight=np.r_[weight, weight, weight],
    )
    assert_evidence_equal(store.snapshot("town").evidence, {k: i.evidence for k, i in expected.items()}, 1e-9)


def _rotation(frame, lat, lon):
    """Per point, the matrix taking its own ENU axes to the frame's (columns)."""
    eye = np.eye(3)
    return np.stack([frame.rotate_velocity(lat, lon, np.broadcast_to(e, (len(lat), 3))) for e in eye], 1)


def test_a_bad_file_fails_the_build_and_stores_nothing(store, spec, client, tmp_path):
    X, V = data(2, n=100)
    good = write(tmp_path / "good.parquet", X, V)
    pq.write_table(pa.table({"x": X[:, 0], "y": X[:, 1], "z": X[:, 2]}), tmp_path / "novel.parquet")
    (tmp_path / "notes.csv").write_text("x,y\n1,2\n")
    (tmp_path / "notes.txt").write_text("x,y\n")
    (tmp_path / "broken.parquet").write_bytes(b"PAR1 not really")
    for paths, message in (
        ([good, tmp_path / "novel.parquet"], "novel.parquet: the table lacks the velocity columns"),
        ([good, tmp_path / "notes.csv"], "notes.csv: the table lacks the velocity columns"),
        (
            [good, tmp_path / "notes.txt"],
            "notes.txt: a build reads .parquet, .arrow, .csv, .csv.gz, .json, .json.gz, .jsonl, "
            ".jsonl.gz files",
        ),
        ([good, tmp_path / "broken.parquet"], "cannot read the files' metadata"),
        ([good, tmp_path / "missing.parquet"], "missing.parquet: no such file"),
        ([], "at least one"),
    ):
        with pytest.raises(ValueError, match=message):
            build(store, "town", paths, client, progress=False)
    with pytest.raises(ValueError, match="must be positive"):
        build(store, "town", [good], client, progress=False, batch_rows=0)
    assert store.region("town").version == 0 and store.snapshot("town").tiles == {}


def test_a_worker_killed_mid_build_changes_nothing(store, spec, tmp_path):
    """SIGKILL one of two worker processes mid-build: Dask recomputes its slices and the
    stored statistics equal those of one upload of every row."""
    X, V = data(6, n=40_000)
    paths = [write(tmp_path / f"p{i}.parquet", X[i::2], V[i::2], rows=500) for i in range(2)]
    store.create_region(spec.model_copy(update={"name": "batch"}))
    RegionMaps(store).upload("batch", "all", X, V)
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        pids = client.run(os.getpid)
        killed, finished = {}, threading.Event()

        def kill_when_some_slices_are_done():
            while not finished.is_set():
                done = client.run_on_scheduler(_slices_done)
                if done >= 6:
                    holder = max(client.has_what().items(), key=lambda item: len(item[1]))[0]
                    os.kill(pids[holder], signal.SIGKILL)
                    killed.update(pid=pids[holder], done=done)
                    return
                time.sleep(0.01)

        killer = threading.Thread(target=kill_when_some_slices_are_done)
        killer.start()
        try:
            result = build(store, "town", paths, client, progress=False, rows_per_task=500, batch_rows=50)
        finally:
            finished.set()  # a failed build must not leave the killer waiting
            killer.join()
        assert 6 <= killed["done"] < 80  # 80 slices: the kill came before the last one
        assert killed["pid"] not in client.run(os.getpid).values()  # a new worker process took over
    assert result["accepted"] == len(X) and result["region_version"] == 1
    assert_evidence_equal(store.snapshot("town").evidence, store.snapshot("batch").evidence, rtol=1e-9)


def _slices_done(dask_scheduler) -> int:
    """Slices finished so far (the count of the tasks' transitions to memory)."""
    prefix = dask_scheduler.task_prefixes.get("slice_evidence")
    return 0 if prefix is None else prefix.state_counts["memory"]


def test_a_scheduler_lost_mid_build_stores_nothing_and_the_rerun_applies_once(store, spec, tmp_path):
    X, V = data(7, n=20_000)
    paths = [write(tmp_path / "p.parquet", X, V, rows=500)]
    file = tmp_path / "scheduler.json"
    options = ["--scheduler-file", str(file), "--no-dashboard"]
    scheduler = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--port", "0", *options],
        stderr=subprocess.DEVNULL,
    )
    worker = None
    try:
        deadline = time.monotonic() + 60
        while not file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        worker = subprocess.Popen(
            [sys.executable, "-m", "distributed.cli.dask_worker", "--nthreads", "1", *options],
            stderr=subprocess.DEVNULL,
        )
        with Client(scheduler_file=str(file), timeout=30) as client:
            client.wait_for_workers(1, timeout=60)

            def kill_when_some_slices_are_done():
                while client.run_on_scheduler(_slices_done) < 3:
                    time.sleep(0.01)
                scheduler.kill()

            threading.Thread(target=kill_when_some_slices_are_done, daemon=True).start()
            with pytest.raises(ClusterLost, match="nothing was stored: run the build again"):
                build(store, "town", paths, client, progress=False, rows_per_task=500, batch_rows=50)
    finally:
        for process in (scheduler, worker):
            if process is not None:
                process.kill()
                process.wait()
    assert store.region("town").version == 0 and store.snapshot("town").tiles == {}

    with (
        LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        first = build(store, "town", paths, client, progress=False)
        again = build(store, "town", paths, client, progress=False)
    assert (first["region_version"], again["replayed"], store.region("town").version) == (1, True, 1)
    expected = {k: i.evidence for k, i in increments(spec, X, V).items()}
    assert_evidence_equal(store.snapshot("town").evidence, expected, rtol=1e-9)


def test_bdf_build_command_on_a_process_cluster(tmp_path):
    """``bdf build`` starts a local cluster of worker processes when no scheduler is given."""
    url = f"sqlite:///{tmp_path / 'data'}"
    store = open_store(url)
    spec = store.create_region(RegionSpec.model_validate(SPEC)).spec
    X, V = data(3, n=400)
    paths = [write(tmp_path / f"p{i}.parquet", X[i::2], V[i::2]) for i in range(2)]
    cmd = [sys.executable, "-m", "clients.cli", "build", "--region", "town", "--store-url", url]
    cmd += ["--workers", "2", "--worker-memory", "1GB", "--rows-per-task", "50", "--batch-rows", "20"]
    run = subprocess.run([*cmd, *map(str, paths)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "400 accepted" in run.stdout and "version 1" in run.stdout
    expected = {k: i.evidence for k, i in increments(spec, X, V).items()}
    assert_evidence_equal(store.snapshot("town").evidence, expected, rtol=1e-9)
    run = subprocess.run(
        [*cmd, str(tmp_path / "nothing.parquet")], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 2 and run.stderr.strip().endswith("nothing.parquet: no such file")
    store.close()
