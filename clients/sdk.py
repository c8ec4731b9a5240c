"""Python SDK for the bdf-maps service: numpy in and out, Arrow or npz on the wire.

``BDFClient`` is synchronous and ``AsyncBDFClient`` has the same methods as coroutines.
Each endpoint is written once, as a generator that yields requests (or pauses) and
receives responses; the two clients only differ in how they send and sleep. Failed
connections and 5xx answers are retried with exponential backoff: uploads carry an
``Idempotency-Key`` derived from the data and chunk index, so a retry never counts twice.

>>> with BDFClient("http://127.0.0.1:8000") as bdf:          # doctest: +SKIP
...     bdf.upload("paris", X, V)
...     pred = bdf.query("paris", X[:10])
...     pred.mean, pred.std
"""

from __future__ import annotations

import asyncio
import hashlib
import io
import json
import sys
import time
from collections.abc import Callable, Generator, Iterable
from dataclasses import dataclass, field, fields
from typing import Any, Literal

import httpx
import numpy as np

from service import wire
from service.wire import ARROW, GEOJSON, JSON, NPZ

RETRY_STATUS = frozenset({500, 502, 503, 504})
Frame = Literal["enu", "wgs84"]


class BDFError(Exception):
    """An error answer of the service (its problem+json), or a failure to reach it.

    ``status`` is the HTTP status (0 when the service could not be reached), ``detail``
    the service's explanation, ``problem`` the whole problem+json document.
    """

    def __init__(self, status: int, title: str, detail: str, problem: dict | None = None):
        super().__init__(f"{status} {title}: {detail}" if status else detail)
        self.status, self.title, self.detail = status, title, detail
        self.problem = problem or {}


@dataclass(frozen=True)
class Region:
    spec: dict  # the region spec's JSON form (bdf.region.spec.RegionSpec validates it)
    version: int
    observations: int
    tiles: int
    created_at: float
    updated_at: float
    #: alpha, beta (the latest found; "auto" until then), fitted_at, evidence_version,
    #: settled, evidence_gap, at_bound
    hyperparameters: dict
    #: that map against its traffic: worst_ratio, implausible_share, grid_step_m (None
    #: before the first map of "auto" hyperparameters)
    plausibility: dict | None = None
    #: the region's horizontal boundary as a closed ring of [lon, lat]
    outline_wgs84: list | None = field(default=None, repr=False)


@dataclass(frozen=True)
class UploadResult:
    """What an upload (all its chunks) did; ``rejected`` counts rows per reason."""

    accepted: int
    rejected: dict[str, int]
    region_version: int
    tiles_updated: int
    chunks: int
    replayed_chunks: int
    upload_ids: list[str] = field(repr=False)
    #: rows without a track id, counted as independent observations, and what the service
    #: said of them
    untracked: int = 0
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Prediction:
    """Mean and std (n, 3) in m/s, region ENU axes; ``known`` False where no data lies
    within the kernel's reach (the map is its prior there). A point outside the region has
    NaN rows and ``known`` False."""

    mean: np.ndarray
    std: np.ndarray
    known: np.ndarray
    region_version: int
    versions_behind: int = 0  # region versions written that the answer's map did not hold yet
    seconds_behind: float = 0.0  # since the first of them was written
    refreshes_behind: int = 0  # the service's maps of the region finished since then (at most 1)
    evidence_gap: float = 0.0  # nats its "auto" hyperparameters lacked from the maximum (0: settled)


@dataclass(frozen=True)
class Grid:
    """A voxel grid: axes x (nx,), y (ny,), z (nz,); mean and std (nx, ny, nz, 3). With
    ``modes``: each traffic class's ``share`` (nx, ny, nz, C), ``mode_mean`` and ``mode_std``
    (nx, ny, nz, C, 3), the shares' std ``share_std`` (nx, ny, nz), ``mode_prior_only``
    (nx, ny, nz, C): no data of the class within the kernel's reach, so its mode there is
    only its prior, and ``mode_heading_noise`` (nx, ny, nz, C, 3): the noise variance within
    ``mode_std^2`` that a known heading narrows (:func:`bdf.sectors.heading_mode`)."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    known: np.ndarray
    region_version: int
    share: np.ndarray | None = None
    mode_mean: np.ndarray | None = None
    mode_std: np.ndarray | None = None
    share_std: np.ndarray | None = None
    mode_prior_only: np.ndarray | None = None
    mode_heading_noise: np.ndarray | None = None

    @property
    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.x, self.y, self.z


@dataclass(frozen=True)
class Tubes:
    """Voxels inside the tube: points, mean, std (k, 3); ``mask`` (nx, ny, nz) on the axes."""

    points: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    mask: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    region_version: int


@dataclass(frozen=True)
class _Request:
    method: str
    path: str
    accept: str = JSON
    params: dict | None = None
    content: bytes | None = None
    content_type: str | None = None
    idempotency_key: str | None = None

    def headers(self) -> dict[str, str]:
        out = {"accept": self.accept}
        if self.content_type:
            out["content-type"] = self.content_type
        if self.idempotency_key:
            out[wire.IDEMPOTENCY_HEADER] = self.idempotency_key
        return out


@dataclass(frozen=True)
class _Pause:
    seconds: float


Call = Generator[_Request | _Pause, httpx.Response | httpx.TransportError | None, Any]


def _pyarrow():
    """pyarrow, imported at the first Arrow body: the SDK imports fast (a CLI's start)."""
    import pyarrow.ipc

    return pyarrow


def _arrow(columns: dict[str, np.ndarray]) -> bytes:
    pa = _pyarrow()
    table = pa.table(columns)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return sink.getvalue().to_pybytes()


def _read_arrow(body: bytes):
    return _pyarrow().ipc.open_stream(body).read_all()


def _vectors(rows: list) -> np.ndarray:
    """JSON rows of 3 numbers (n, 3), a null row (a point outside the region) as NaN."""
    return np.array([[np.nan] * 3 if row is None else row for row in rows], float).reshape(-1, 3)


def _stack(table, names) -> np.ndarray:
    return np.stack([table.column(n).to_numpy() for n in names], axis=1).astype(float)


def _points(X, name: str = "X") -> np.ndarray:
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {X.shape}")
    return X


def _position_columns(X: np.ndarray, frame: Frame) -> dict[str, np.ndarray]:
    if frame not in ("enu", "wgs84"):
        raise ValueError(f"frame must be 'enu' or 'wgs84', got {frame!r}")
    names = wire.ENU_COLUMNS if frame == "enu" else wire.WGS84_COLUMNS
    return {n: np.ascontiguousarray(X[:, i]) for i, n in enumerate(names)}


def _csv(values, n: int, name: str) -> str:
    values = np.atleast_1d(np.asarray(values, dtype=float)).ravel()
    if len(values) == 1 and n == 3:
        values = np.repeat(values, 3)
    if len(values) != n:
        raise ValueError(f"{name} needs {n} numbers, got {len(values)}")
    return ",".join(repr(float(v)) for v in values)


def _grid_params(step, bbox) -> dict[str, str]:
    params = {"step": _csv(step, 3, "step")}
    if bbox is not None:
        params["bbox"] = _csv(bbox, 6, "bbox")
    return params


def _npz(body: bytes) -> dict[str, np.ndarray]:
    """The arrays of an npz answer; never unpickles (a body is data, not code)."""
    with np.load(io.BytesIO(body), allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


def _version(response: httpx.Response) -> int:
    return int(response.headers[wire.VERSION_HEADER])


def _lag(response: httpx.Response) -> tuple[int, float, int, float]:
    """How far the answer's map was behind the region (versions, seconds, refreshes) and
    its hyperparameters from the evidence maximum (nats)."""
    headers = response.headers
    return (
        int(headers[wire.VERSIONS_BEHIND_HEADER]),
        float(headers[wire.SECONDS_BEHIND_HEADER]),
        int(headers[wire.REFRESHES_BEHIND_HEADER]),
        float(headers[wire.EVIDENCE_GAP_HEADER]),
    )


def _json_body(body) -> dict:
    return {"content": json.dumps(body).encode(), "content_type": JSON}


def _observations_body(X, V, noise, weight, track, t, frame: Frame) -> bytes:
    columns = {
        **_position_columns(X, frame),
        **{c: np.ascontiguousarray(V[:, j]) for j, c in enumerate(wire.VELOCITY_COLUMNS)},
    }
    if noise is not None:
        columns["input_noise_std"] = noise
    if weight is not None:
        columns["sample_weight"] = weight
    if track is not None:
        columns["track"], columns["t"] = track, t
    return _arrow(columns)


def _per_point(value, n: int, name: str) -> np.ndarray | None:
    if value is None:
        return None
    try:
        return np.broadcast_to(np.asarray(value, dtype=float), (n,)).copy()
    except ValueError:
        raise ValueError(
            f"{name} must be one number or one per point ({n}), got shape {np.shape(value)}"
        ) from None


def _observations(X, V, noise, weight, track, t):
    X, V = _points(X), _points(V, "V")
    if len(X) != len(V):
        raise ValueError(f"{len(X)} positions but {len(V)} velocities")
    if len(X) == 0:
        raise ValueError("no observations to send")
    if (track is None) != (t is None):
        raise ValueError("track and t go together: the service weighs a track's rows by their times")
    if track is not None:
        track = np.asarray(track)
        if track.dtype.kind not in "iuUO" or track.shape != (len(X),):
            raise ValueError(
                f"track must hold one string or integer id per point ({len(X)}), "
                f"got {track.dtype} {track.shape}"
            )
        if track.dtype.kind in "iu":
            track = track.astype(np.int64)
        t = _per_point(t, len(X), "t")
    return (
        X,
        V,
        _per_point(noise, len(X), "input_noise_std"),
        _per_point(weight, len(X), "sample_weight"),
        track,
        t,
    )


def _upload_key(chunk_size: int, kind: str, *arrays) -> str:
    """Same data, same keys: a rerun of an interrupted upload skips the chunks already applied."""
    h = hashlib.sha256(kind.encode())
    for a in arrays:
        if a is not None:
            h.update(np.ascontiguousarray(a.astype(str) if a.dtype == object else a).tobytes())
    h.update(str(chunk_size).encode())
    return h.hexdigest()[:32]


def _progress_bar(total: int, desc: str, enabled: bool | None):
    """A tqdm bar on a terminal (``enabled=None``), never when output is piped."""
    from tqdm.auto import tqdm

    disable = (not sys.stderr.isatty()) if enabled is None else not enabled
    return tqdm(total=total, desc=desc, unit="obs", unit_scale=True, disable=disable)


class _Endpoints:
    """The endpoints and the retries, once for both clients; ``_run`` drives a call: it
    sends each request and sends back the response, or the connection error."""

    _run: Callable[[Call], Any]
    _http_class: type[httpx.Client] | type[httpx.AsyncClient]

    def __init__(
        self,
        url: str = "http://127.0.0.1:8000",
        token: str | None = None,
        *,
        timeout_s: float = 120.0,
        retries: int = 4,
        backoff_s: float = 0.25,
        transport: httpx.BaseTransport | httpx.AsyncBaseTransport | None = None,
    ):
        self.url = url.rstrip("/")
        self._delays = _backoff(retries, backoff_s)
        self._http = self._http_class(
            base_url=self.url, headers=_headers(token), timeout=timeout_s, transport=transport
        )
        # read your writes: the newest version each region reached through this client;
        # queries ask the service for at least that version (it waits for its map)
        self._written: dict[str, int] = {}

    def _wrote(self, name: str, version: int) -> None:
        self._written[name] = max(self._written.get(name, 0), int(version))

    def _read_params(self, name: str, params: dict | None = None) -> dict:
        out = dict(params or {})
        if name in self._written:
            out["min_version"] = str(self._written[name])
        return out

    def _retrying(self, call: Call) -> Call:
        """``call`` with each request retried after connection errors and 5xx, with backoff."""
        try:
            step = next(call)
        except StopIteration as done:
            return done.value
        while True:
            value = (yield step) if isinstance(step, _Pause) else (yield from self._attempts(step))
            try:
                step = call.send(value)
            except StopIteration as done:
                return done.value

    def _attempts(self, request: _Request):
        delays = iter(self._delays)
        while True:
            outcome = yield request
            failed = isinstance(outcome, httpx.TransportError)
            if not failed and outcome.status_code not in RETRY_STATUS:
                _raise_for_problem(outcome)
                return outcome
            delay = next(delays, None)
            if delay is None:
                if failed:
                    raise _unreachable(self.url, outcome) from outcome
                _raise_for_problem(outcome)
            yield _Pause(delay)

    # -- regions ------------------------------------------------------------------------------
    def regions(self) -> list[Region]:
        return self._run(self._json("GET", "/v1/regions", parse=lambda js: [_region(r) for r in js]))

    def region(self, name: str) -> Region:
        return self._run(self._json("GET", f"/v1/regions/{name}", parse=_region))

    def create_region(self, spec) -> Region:
        """Create a region from its spec: a dict of its JSON form, or a
        :class:`bdf.region.spec.RegionSpec` (checked here before it is sent)."""
        body = spec.model_dump(mode="json") if hasattr(spec, "model_dump") else dict(spec)
        return self._run(self._json("POST", "/v1/regions", json=body, parse=_region))

    def delete_region(self, name: str) -> None:
        return self._run(self._json("DELETE", f"/v1/regions/{name}", parse=lambda js: None))

    def fit_hyperparameters(self, name: str) -> Region:
        """The region's map at its current version, now: its "auto" alpha and beta at the
        evidence maximum of all its data (every refresh after an upload finds them too);
        returns the region, which records them."""
        region = self._run(self._json("POST", f"/v1/regions/{name}/hyperparameters", parse=_region))
        self._wrote(name, region.version)
        return region

    def tiles(self, name: str) -> dict:
        """``{"region_version", "tiles": [{"key", "version", "count", "points", "bytes", ...}]}``."""
        return self._run(self._json("GET", f"/v1/regions/{name}/tiles"))

    def health(self) -> bool:
        """True when the service answers and its store is reachable."""
        return self._run(self._json("GET", "/readyz", parse=lambda js: js.get("status") == "ready"))

    def job(self, job_id: str) -> dict:
        return self._run(self._json("GET", f"/v1/jobs/{job_id}"))

    # -- data ---------------------------------------------------------------------------------
    def upload(
        self,
        name: str,
        X,
        V,
        *,
        input_noise_std=None,
        sample_weight=None,
        track=None,
        t=None,
        frame: Frame = "enu",
        chunk_size: int = 200_000,
        key: str | None = None,
        progress: bool | None = None,
    ) -> UploadResult:
        """Add observations: positions ``X`` (n, 3) ENU metres or lat, lon, alt_m with
        ``frame="wgs84"``; velocities ``V`` (n, 3) east, north, up m/s; ``track`` (n,)
        string or integer id of each row's track (aircraft, flight) and ``t`` (n,) its
        time in seconds: the service weighs a track's correlated rows itself (rows without
        them count as independent observations, and ``warnings`` says so);
        ``sample_weight`` per row (with ``track``: times its track weight). Sent in chunks
        of ``chunk_size`` with keys ``{key}-{i}`` (a track may be cut between chunks);
        ``key`` defaults to a hash of the data, so running the same upload again applies
        nothing twice."""
        return self._run(
            self._upload(
                name, X, V, input_noise_std, sample_weight, track, t, frame, chunk_size, key, progress
            )
        )

    def retract(
        self,
        name: str,
        X,
        V,
        *,
        input_noise_std=None,
        sample_weight=None,
        track=None,
        t=None,
        frame: Frame = "enu",
        chunk_size: int = 200_000,
        key: str | None = None,
        progress: bool | None = None,
    ) -> UploadResult:
        """Undo an :meth:`upload` exactly (admin scope), e.g. of a vehicle whose sensor was
        broken: called with the upload's own arguments (rows, chunk size, key), each chunk
        names the upload it retracts and carries its rows again, which the service checks
        against its ledger. The map becomes the map without them; running it again
        applies nothing twice."""
        return self._run(
            self._upload(
                name,
                X,
                V,
                input_noise_std,
                sample_weight,
                track,
                t,
                frame,
                chunk_size,
                key,
                progress,
                "retractions",
            )
        )

    def fit(
        self,
        name: str,
        X,
        V,
        *,
        input_noise_std=None,
        sample_weight=None,
        track=None,
        t=None,
        frame: Frame = "enu",
        key: str | None = None,
        wait: bool = True,
        poll_s: float = 0.5,
        progress: bool | None = None,
    ) -> UploadResult | dict:
        """Replace the region's map with these observations (one request). A large fit runs
        as a job on the server: with ``wait`` the client polls it and returns its result;
        without, it returns the job (``{"id", "state", "progress", ...}``). ``track`` and
        ``t`` as for :meth:`upload`."""
        return self._run(
            self._fit(
                name, X, V, input_noise_std, sample_weight, track, t, frame, key, wait, poll_s, progress
            )
        )

    # -- maps ---------------------------------------------------------------------------------
    def query(
        self,
        name: str,
        X,
        *,
        frame: Frame = "enu",
        transport: Literal["arrow", "json"] = "arrow",
        heading_deg=None,
    ):
        """Predictive mean and std at points ``X`` (n, 3); returns :class:`Prediction`.
        ``heading_deg`` (one, or one per point): the mode of traffic flying it."""
        return self._run(self._query(name, _points(X), frame, transport, heading_deg))

    def grid(self, name: str, step, bbox=None, *, modes: bool = False) -> Grid:
        """Mean and std on the voxel grid ``bbox`` (xmin, ymin, zmin, xmax, ymax, zmax; default
        the region) with ``step`` metres (one number or three), as npz; ``modes``: each
        traffic class's too."""
        return self._run(self._grid(name, step, bbox, modes))

    def tubes(
        self,
        name: str,
        max_std_mps: float,
        step,
        bbox=None,
        component: Literal["all", "e", "n", "u"] = "all",
    ) -> Tubes:
        """The voxels whose predictive std (of all components, or one) is below ``max_std_mps``."""
        return self._run(self._tubes(name, max_std_mps, step, bbox, component, NPZ))

    def tubes_geojson(self, name: str, max_std_mps: float, step, bbox=None, component: str = "all") -> dict:
        """The tube as a GeoJSON FeatureCollection of points (lon, lat, alt)."""
        return self._run(self._tubes(name, max_std_mps, step, bbox, component, GEOJSON))

    def assess_route(
        self,
        name: str,
        route,
        *,
        max_std_mps: float | None = None,
        vehicle: str | dict | None = None,
        frame: Frame = "enu",
        times_s=None,
        heading_deg=None,
        route_name: str | None = None,
    ) -> dict:
        """A route's metrics on the map, per segment and in total, and whether ``vehicle``
        ("evtol", "fixed-wing" or its fields) can fly it. ``route``: points (n, 3) in
        ``frame``, or a GeoJSON LineString Feature or FeatureCollection (such as
        :meth:`planner.routes.RoutePlan.geojson`'s, which holds two: ``route_name`` picks one
        by its ``name`` property; its properties may hold the other arguments, which the
        keywords override)."""
        if isinstance(route, dict):
            feature = _one_route(route, route_name)
            given = {
                "max_std_mps": max_std_mps,
                "vehicle": vehicle,
                "times_s": times_s,
                "heading_deg": heading_deg,
            }
            properties = {
                **feature.get("properties", {}),
                **{k: v for k, v in given.items() if v is not None},
            }
            body, media = {**feature, "properties": properties}, GEOJSON
        else:
            body = {"frame": frame, "points": _points(route, "route").tolist(), "max_std_mps": max_std_mps}
            for key, value in (("vehicle", vehicle), ("times_s", times_s), ("heading_deg", heading_deg)):
                if value is not None:
                    body[key] = np.asarray(value, float).tolist() if key != "vehicle" else value
            media = JSON
        return self._run(self._assess(name, body, media))

    def slice_png(
        self,
        name: str,
        alt_m: float,
        layer: Literal["mean", "std", "tube"] = "mean",
        component: Literal["e", "n", "u"] = "e",
        max_std_mps: float = 1.0,
        bbox=None,
        step: float | None = None,
    ) -> bytes:
        """PNG of the horizontal slice at ``alt_m`` (what ``/viewer`` shows); ``bbox`` is
        (xmin, ymin, xmax, ymax) in ENU metres, ``step`` the cell size (default: automatic)."""
        params = {"alt_m": repr(float(alt_m)), "layer": layer, "component": component}
        params["max_std_mps"] = repr(float(max_std_mps))
        if bbox is not None:
            params["bbox"] = ",".join(repr(float(v)) for v in bbox)
        if step is not None:
            params["step"] = repr(float(step))
        return self._run(
            self._bytes(f"/v1/regions/{name}/slice.png", wire.PNG, self._read_params(name, params))
        )

    # -- the calls ----------------------------------------------------------------------------
    def _bytes(self, path: str, accept: str, params: dict) -> Call:
        response = yield _Request("GET", path, accept=accept, params=params)
        return response.content

    def _json(self, method: str, path: str, *, json=None, parse=lambda js: js) -> Call:
        body = {} if json is None else _json_body(json)
        response = yield _Request(method, path, **body)
        return parse(response.json() if response.content else None)

    def _assess(self, name: str, body: dict, media: str) -> Call:
        path = f"/v1/regions/{name}/routes/assess"
        content = json.dumps(body).encode()
        response = yield _Request(
            "POST", path, params=self._read_params(name), content=content, content_type=media
        )
        return response.json()

    def _upload(
        self, name, X, V, noise, weight, track, t, frame, chunk_size, key, progress, route="observations"
    ) -> Call:
        rows = X, V, noise, weight, track, t = _observations(X, V, noise, weight, track, t)
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        key = key or _upload_key(chunk_size, "observations", *rows)
        results = []
        verb = "upload" if route == "observations" else "retract"
        with _progress_bar(len(X), f"{verb} {name}", progress) as bar:
            for i, start in enumerate(range(0, len(X), chunk_size)):
                part = slice(start, start + chunk_size)
                response = yield _Request(
                    "POST",
                    f"/v1/regions/{name}/{route}",
                    content=_observations_body(
                        *(None if a is None else a[part] for a in rows),
                        frame,
                    ),
                    content_type=ARROW,
                    idempotency_key=f"{key}-{i}",
                )
                results.append(response.json())
                self._wrote(name, results[-1]["region_version"])
                bar.update(len(X[part]))
        return _summary(results)

    def _fit(self, name, X, V, noise, weight, track, t, frame, key, wait, poll_s, progress) -> Call:
        rows = _observations(X, V, noise, weight, track, t)
        response = yield _Request(
            "POST",
            f"/v1/regions/{name}/fit",
            content=_observations_body(*rows, frame),
            content_type=ARROW,
            idempotency_key=key or _upload_key(len(rows[0]), "fit", *rows),
        )
        if response.status_code != 202:
            self._wrote(name, response.json()["region_version"])
            return _summary([response.json()])
        job = response.json()
        if not wait:
            return job
        with _progress_bar(100, f"fit {name}", progress) as bar:
            while job["state"] in ("queued", "running"):
                yield _Pause(poll_s)
                job = (yield _Request("GET", f"/v1/jobs/{job['id']}")).json()
                bar.update(round(100 * job["progress"]) - bar.n)
        if job["state"] == "failed":
            raise BDFError(500, "fit job failed", job.get("error") or "unknown error", job)
        self._wrote(name, job["result"]["region_version"])
        return _summary([job["result"]])

    def _query(self, name, X, frame, transport, heading_deg) -> Call:
        path, params = f"/v1/regions/{name}/query", self._read_params(name)
        if heading_deg is not None:
            heading_deg = np.broadcast_to(np.asarray(heading_deg, float), (len(X),))
        if transport == "json":
            body = {"frame": frame, "points": X.tolist()}
            if heading_deg is not None:
                body["heading_deg"] = heading_deg.tolist()
            response = yield _Request("POST", path, params=params, **_json_body(body))
            js = response.json()
            return Prediction(
                _vectors(js["mean"]),
                _vectors(js["std"]),
                np.array(js["known"], bool),
                js["region_version"],
                *_lag(response),
            )
        if transport != "arrow":
            raise ValueError(f"transport must be 'arrow' or 'json', got {transport!r}")
        response = yield _Request(
            "POST",
            path,
            accept=ARROW,
            params=params,
            content=_arrow(
                _position_columns(X, frame)
                | ({} if heading_deg is None else {"heading_deg": np.ascontiguousarray(heading_deg)})
            ),
            content_type=ARROW,
        )
        table = _read_arrow(response.content)
        return Prediction(
            _stack(table, wire.VELOCITY_COLUMNS),
            _stack(table, wire.STD_COLUMNS),
            table.column("known").to_numpy(zero_copy_only=False).astype(bool),
            _version(response),
            *_lag(response),
        )

    def _grid(self, name, step, bbox, modes) -> Call:
        params = self._read_params(name, _grid_params(step, bbox) | ({"modes": "true"} if modes else {}))
        response = yield _Request("GET", f"/v1/regions/{name}/grid", accept=NPZ, params=params)
        a = _npz(response.content)
        names = ("share", "mode_mean", "mode_std", "share_std", "mode_prior_only", "mode_heading_noise")
        per_class = tuple(a[n] for n in names) if modes else (None,) * len(names)
        return Grid(a["x"], a["y"], a["z"], a["mean"], a["std"], a["known"], _version(response), *per_class)

    def _tubes(self, name, max_std_mps, step, bbox, component, media) -> Call:
        params = {**_grid_params(step, bbox), "max_std_mps": repr(float(max_std_mps)), "component": component}
        params = self._read_params(name, params)
        response = yield _Request("GET", f"/v1/regions/{name}/tubes", accept=media, params=params)
        if media == GEOJSON:
            return response.json()
        a = _npz(response.content)
        return Tubes(a["points"], a["mean"], a["std"], a["mask"], a["x"], a["y"], a["z"], _version(response))


def _region(js: dict) -> Region:
    """The region view; fields a newer service adds are left out (this SDK keeps working)."""
    return Region(**{f.name: js[f.name] for f in fields(Region) if f.name in js})


def _summary(results: Iterable[dict]) -> UploadResult:
    results = list(results)
    rejected: dict[str, int] = {}
    for r in results:
        for reason, n in r["rejected"].items():
            rejected[reason] = rejected.get(reason, 0) + n
    return UploadResult(
        accepted=sum(r["accepted"] for r in results),
        rejected=rejected,
        region_version=max(r["region_version"] for r in results),
        tiles_updated=sum(r["tiles_updated"] for r in results),
        chunks=len(results),
        replayed_chunks=sum(bool(r["replayed"]) for r in results),
        upload_ids=[r["upload_id"] for r in results],
        untracked=sum(r.get("untracked", 0) for r in results),
        warnings=list(dict.fromkeys(w for r in results for w in r.get("warnings", []))),
    )


def _raise_for_problem(response: httpx.Response) -> None:
    if response.status_code < 400:
        return
    try:
        problem = response.json()
    except ValueError:
        problem = {}
    if not isinstance(problem, dict):
        problem = {}
    raise BDFError(
        response.status_code,
        problem.get("title", response.reason_phrase),
        problem.get("detail", response.text[:300]),
        problem,
    )


def _backoff(retries: int, backoff_s: float) -> list[float]:
    """Pauses before each retry: ``backoff_s`` doubling, ``retries`` of them."""
    if retries < 0 or backoff_s < 0:
        raise ValueError(f"retries and backoff_s must not be negative, got {retries}, {backoff_s}")
    return [backoff_s * 2**i for i in range(retries)]


def _unreachable(url, exc: Exception) -> BDFError:
    return BDFError(0, "unreachable", f"cannot reach the bdf service at {url}: {type(exc).__name__}: {exc}")


def _headers(token: str | None) -> dict[str, str]:
    return {"authorization": f"Bearer {token}"} if token else {}


class BDFClient(_Endpoints):
    """Synchronous client. ``token``: a bearer token of the needed scope (none for an open
    local service). Use as a context manager, or call :meth:`close`."""

    _http_class = httpx.Client

    def _run(self, call: Call):
        call = self._retrying(call)
        try:
            step = next(call)
            while True:
                if isinstance(step, _Pause):
                    time.sleep(step.seconds)
                    step = call.send(None)
                    continue
                try:
                    outcome = self._http.send(_build(self._http, step))
                except httpx.TransportError as exc:
                    outcome = exc
                step = call.send(outcome)
        except StopIteration as done:
            return done.value

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> BDFClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class AsyncBDFClient(_Endpoints):
    """The same methods as :class:`BDFClient`, as coroutines (``await client.query(...)``)."""

    _http_class = httpx.AsyncClient

    async def _run(self, call: Call):
        call = self._retrying(call)
        try:
            step = next(call)
            while True:
                if isinstance(step, _Pause):
                    await asyncio.sleep(step.seconds)
                    step = call.send(None)
                    continue
                try:
                    outcome = await self._http.send(_build(self._http, step))
                except httpx.TransportError as exc:
                    outcome = exc
                step = call.send(outcome)
        except StopIteration as done:
            return done.value

    async def aclose(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> AsyncBDFClient:
        return self

    async def __aexit__(self, *exc) -> None:
        await self.aclose()


def _build(http: httpx.Client | httpx.AsyncClient, request: _Request) -> httpx.Request:
    return http.build_request(
        request.method,
        request.path,
        params=request.params,
        content=request.content,
        headers=request.headers(),
    )


def _one_route(doc: dict, name: str | None) -> dict:
    """The route of a GeoJSON document to assess: itself, the one LineString of a
    collection, or the one named ``name`` (``properties.name``)."""
    if doc.get("type") != "FeatureCollection":
        return doc
    lines = [
        f
        for f in doc.get("features") or []
        if isinstance(f, dict) and (f.get("geometry") or {}).get("type") == "LineString"
    ]
    names = [str((f.get("properties") or {}).get("name", i)) for i, f in enumerate(lines)]
    if name is not None:
        if name not in names:
            raise ValueError(f"the collection holds no route named {name!r} (it holds {', '.join(names)})")
        return lines[names.index(name)]
    if len(lines) != 1:
        raise ValueError(
            f"the collection holds {len(lines)} routes ({', '.join(names)}): pick one with --route "
            "(route_name in the SDK)"
        )
    return lines[0]
