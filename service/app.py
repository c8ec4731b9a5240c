"""The HTTP API (v1): regions, observations, fits, queries, grids, tubes, slices, tiles, routes.

Routes stay thin: decoding and encoding live in :mod:`service.formats`, the maps in
:mod:`service.maps` and :mod:`bdf.region`, storage in :mod:`service.store`. Every route
declares its scope (``x-scope`` in the OpenAPI document). Work that takes CPU or the
database runs in a lane's threads (:mod:`service.lanes`: light or heavy, bounded, shed
when full); on a local store a light step that only reads runs on the event loop, where it
costs less than the hand-off to a thread. ``/healthz`` and ``/metrics`` answer from the
event loop alone: never behind heavy work (on a local store, behind the light reads ahead).
"""

from __future__ import annotations

import functools
import gc
import hashlib
import html
import json
import logging
import pathlib
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Annotated, Literal

import anyio
import anyio.to_thread
import numpy as np
from fastapi import APIRouter, Depends, FastAPI, Header, Path, Query, Request, Response
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel, Field

from bdf import sectors
from bdf.region.route import CHUNK_SAMPLES, ENVELOPE_SAMPLES_PER_POINT, MAX_ROUTE_POINTS, SAMPLE_M
from bdf.region.route import samples as route_samples
from bdf.region.spec import REGION_NAME, REGION_NAME_RULE, RegionSpec, key_str
from service import formats, lanes, problems, slices, webmap, wire
from service.auth import PUBLIC, require
from service.jobs import Jobs
from service.lanes import Heavy, Lanes, Threaded, Waiting
from service.maps import RegionMaps, upload_digest, upload_kind
from service.problems import Problem
from service.settings import Settings
from service.store import MapStore, RegionInfo, open_store
from service.telemetry import Metrics, RequestMiddleware
from service.wire import ARROW, GEOJSON, JSON, NPZ, PARQUET, PNG

log = logging.getLogger("bdf.service")
VIEWER_HTML = (pathlib.Path(__file__).parent / "viewer.html").read_text()
#: the viewer's script, styles and worker (MapLibre GL JS, shipped in the package)
STATIC = {
    name: (pathlib.Path(__file__).parent / "static" / name, media)
    for name, media in (
        ("maplibre-gl-csp.js", "text/javascript"),
        ("maplibre-gl-csp-worker.js", "text/javascript"),
        ("maplibre-gl.css", "text/css"),
        ("maplibre-gl-LICENSE.txt", "text/plain"),
    )
}


def viewer_policy(basemap: str | None) -> str:
    """The viewer's Content-Security-Policy: its own scripts, styles, worker and tiles; a
    basemap's origin too when one is set (its style, tiles and fonts)."""
    other = " https:" if basemap else ""
    return (
        f"default-src 'none'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
        f"img-src 'self' data: blob:{other}; worker-src 'self' blob:; connect-src 'self'{other}; "
        "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
    )


RegionName = Annotated[str, Path(pattern=REGION_NAME, description=f"region name: {REGION_NAME_RULE}")]


#: what an Arrow or Parquet body of observations holds
OBSERVATION_COLUMNS = (
    "a table with the columns x, y, z (ENU m) or lat, lon, alt_m; ve, vn, vu (m/s); optional "
    "input_noise_std, sample_weight, and track (string or integer id) with t (seconds): the service "
    "weighs the rows of a track itself (about one observation per kernel width flown); rows without "
    "one count as independent observations, and the answer says how many (untracked, warnings)"
)


def _body_doc(model: type[BaseModel], binary: tuple[str, ...], columns: str = "") -> dict:
    """The request body in OpenAPI: the JSON model and the binary media types also taken
    (``columns``: what their tables hold)."""
    content = {JSON: {"schema": model.model_json_schema(ref_template="#/components/schemas/{model}")}}
    schema = {"type": "string", "format": "binary", **({"description": columns} if columns else {})}
    content.update({m: {"schema": schema} for m in binary})
    return {"requestBody": {"required": True, "content": content}}


def scoped(scope: str, responses: dict | None = None, **extra) -> dict:
    """Route keyword arguments declaring its scope (enforced and documented) and its
    responses: ``responses`` and the errors every route may answer (problem+json)."""
    out = {
        "openapi_extra": {"x-scope": scope, **extra},
        "responses": {**problems.ERRORS, **(responses or {})},
    }
    if scope != PUBLIC:
        out["dependencies"] = [require(scope)]
    return out


class Hyperparameters(BaseModel):
    """alpha and beta: the spec's fixed values, or ("auto") those found on the region's
    data at ``evidence_version``, at ``fitted_at``: the evidence maximum (``settled``), or
    within ``evidence_gap`` nats (under one) of it while the background refresh settles
    them ("auto" until the first). A directional region has a row per component triple:
    the map with one class, then each class (:class:`bdf.posterior.Mixture`)."""

    alpha: Literal["auto"] | float | list[float] | list[list[float]]
    beta: Literal["auto"] | float | list[float] | list[list[float]]
    fitted_at: float | None
    evidence_version: int | None
    settled: bool | None
    evidence_gap: float | None
    log_evidence: list[float] | list[list[float]] | None
    at_bound: bool | None = Field(
        None,
        description="the search ended at its range's floor or top: the evidence could not place "
        "alpha / beta, and the map there is its prior's as much as its data's",
    )


class Plausibility(BaseModel):
    """The map of ``evidence_version`` against the traffic it learnt from
    (:func:`bdf.region.map.plausibility`): no mean, and no mode with a share of at least
    0.05, should fly faster horizontally than 1.1 x the 99.9th percentile of the horizontal
    speeds of the rows within 1 km of its altitude (the envelope's speed where none is)."""

    worst_ratio: float = Field(description="the fastest mean or mode over that bound, anywhere in the box")
    implausible_share: float = Field(description="the share of the judging grid's voxels above the bound")
    grid_step_m: list[float] = Field(description="the judging grid's steps (x, y, z)")


class RegionView(BaseModel):
    spec: RegionSpec
    version: int
    observations: int
    tiles: int
    created_at: float
    updated_at: float
    hyperparameters: Hyperparameters
    plausibility: Plausibility | None = Field(
        None, description="how the map of the hyperparameters' evidence_version compares with its traffic"
    )
    outline_wgs84: list[list[float]] = Field(
        description="the region's horizontal boundary at its lowest altitude: a closed ring of [lon, lat]"
    )


class UploadView(BaseModel):
    accepted: int
    rejected: dict[str, int]
    upload_id: str
    kind: Literal["observations", "fit", "retraction"]
    region_version: int
    tiles_updated: int
    replayed: bool
    untracked: int = Field(
        0, description="accepted rows without a track id, counted as independent observations"
    )
    warnings: list[str] = Field(default_factory=list, description="what the client should know of its data")


class JobView(BaseModel):
    id: str
    region: str
    upload_id: str
    state: Literal["queued", "running", "succeeded", "failed"]
    progress: float
    result: UploadView | None
    error: str | None
    created_at: float
    finished_at: float | None


def _view(info: RegionInfo) -> dict:
    alpha, beta = info.hyperparameters()
    fitted = info.hyper or {}
    return {
        "spec": info.spec.model_dump(mode="json"),
        "version": info.version,
        "observations": info.observations,
        "tiles": info.tiles,
        "created_at": info.created_at,
        "updated_at": info.updated_at,
        "hyperparameters": {
            "alpha": alpha,
            "beta": beta,
            "fitted_at": fitted.get("fitted_at"),
            "evidence_version": fitted.get("evidence_version"),
            "settled": fitted.get("settled", True) if fitted else None,
            "evidence_gap": fitted.get("evidence_gap", 0.0) if fitted else None,
            "log_evidence": fitted.get("log_evidence"),
            "at_bound": fitted.get("at_bound") if fitted else None,
        },
        "plausibility": fitted.get("plausibility"),
        "outline_wgs84": webmap.outline(info.spec).round(7).tolist(),
    }


@dataclass(frozen=True)
class Service:
    """The parts a route works with: what the app was made with (``app.state.service``)."""

    settings: Settings
    maps: RegionMaps
    jobs: Jobs
    lanes: Lanes
    metrics: Metrics

    async def run(self, step, heavy: bool = False, write: bool = False, body_bytes: int = 0):
        """``step()`` in a lane (:mod:`service.lanes`): the light one unless ``heavy`` (on
        the event loop if it only reads, its request's body of ``body_bytes`` is small and
        the store is local), one ``write`` at a time; a light step that returns
        :class:`Heavy` goes on in the heavy lane."""
        return await self.lanes.run(step, heavy, write, body_bytes)

    def limits(self, rows: int) -> formats.Limits:
        """What one request body may decode into: ``rows`` rows at most."""
        s = self.settings
        return formats.Limits(rows, int(s.max_decoded_mb * 2**20), int(s.max_json_mb * 2**20))


async def service(request: Request) -> Service:
    # every dependency is a coroutine: FastAPI hands a plain function to a worker thread,
    # a hand-off per request that costs more CPU than the dependency (:func:`auth.require`)
    return request.app.state.service


ServiceDep = Annotated[Service, Depends(service)]


class MapAnswer:
    """The headers of an answer computed from a region's map: its ETag, which names
    everything the answer depends on (the map's region instance and version, the request's
    path, query, Accept, Content-Type and body), and the version it came from and how far
    that is behind the region's newest (versions, seconds since the first of them was
    written, and this process's maps of the region finished since then), which /metrics
    counts too, and the nats its "auto" hyperparameters lack from
    the evidence maximum (0 once settled; the ETag tells a settled map from the one before)."""

    def __init__(self, request: Request, svc: Service):
        self.request, self.svc, self.body = request, svc, b""
        self._digest: str | None = None  # of the request, once its body is read

    def etag(self, region_id: str, version: int, settled: bool) -> str:
        if self._digest is None:  # the 304 check and the answer's headers both name it
            h = hashlib.sha256()
            request = self.request
            for part in (
                request.scope["path"],
                repr(sorted(request.query_params.multi_items())),
                request.headers.get("accept", ""),
                request.headers.get("content-type", ""),
            ):
                h.update(part.encode() + b"\0")
            h.update(self.body)
            self._digest = h.hexdigest()[:20]
        return f'W/"{region_id}.{version}{"" if settled else "~"}.{self._digest}"'

    def region_or_304(self, name: str) -> tuple[RegionInfo, Response | None]:
        """The region's info, and a 304 if the client's ETag names its current state and
        this request."""
        info = self.svc.maps.store.region(name)
        etag = self.etag(info.region_id, info.version, self.svc.maps.settled(info))
        header = self.request.headers.get("if-none-match")
        tags = [t.strip().removeprefix("W/") for t in header.split(",")] if header else []
        if "*" in tags or etag.removeprefix("W/") in tags:
            return info, Response(status_code=304, headers={"ETag": etag})
        return info, None

    def headers(self, pred) -> dict:
        self.svc.metrics.answered(pred.behind, pred.behind_s, pred.refreshes_behind)
        return {
            "ETag": self.etag(pred.region_id, pred.version, pred.evidence_gap == 0),
            wire.VERSION_HEADER: str(pred.version),
            wire.VERSIONS_BEHIND_HEADER: str(pred.behind),
            wire.SECONDS_BEHIND_HEADER: f"{pred.behind_s:.3f}",
            wire.REFRESHES_BEHIND_HEADER: str(pred.refreshes_behind),
            wire.EVIDENCE_GAP_HEADER: f"{pred.evidence_gap:.4g}",
        }


async def map_answer(request: Request, svc: ServiceDep) -> MapAnswer:
    return MapAnswer(request, svc)


AnswerDep = Annotated[MapAnswer, Depends(map_answer)]

MinVersion = Annotated[
    int,
    Query(
        ge=0,
        description="answer from at least this region version (read your writes): waits for its "
        "map; without it the newest ready map answers while a refresh runs (X-Region-Version says which)",
    ),
]
WithModes = Annotated[
    bool, Query(description="add every traffic class (heading sectors, then slow): share, mean, std")
]

#: a number as the comma-separated query parameters take it (two exponent digits: finite)
NUMBER = r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]{1,2})?"
POSITIVE = r"(?:0*[1-9][0-9]*(?:\.[0-9]*)?|0*\.[0-9]*[1-9][0-9]*)(?:[eE][-+]?[0-9]{1,2})?"
BOX3 = rf"^{NUMBER}(?:,{NUMBER}){{5}}$"
BOX2 = rf"^{NUMBER}(?:,{NUMBER}){{3}}$"
STEP = rf"^{POSITIVE}(?:,{POSITIVE},{POSITIVE})?$"
#: what the patterns mean, in a 422
PATTERNS = {
    REGION_NAME: REGION_NAME_RULE,
    BOX3: "6 comma-separated numbers",
    BOX2: "4 comma-separated numbers",
    STEP: "1 or 3 comma-separated positive numbers",
}


def _floats(text: str, n: int, name: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise Problem(422, f"{name} must be {n} comma-separated numbers, got {text!r}") from None
    if len(values) == 1 and n == 3:
        values = np.repeat(values, 3)
    if len(values) != n or not np.isfinite(values).all():
        raise Problem(422, f"{name} must be {n} finite comma-separated numbers, got {text!r}")
    return values


@dataclass(frozen=True)
class GridParams:
    """A voxel grid over a box: ``step`` (3,) metres, and ``bbox`` (6,) in region ENU
    metres (None: the region's box); the map of at least ``min_version``."""

    step: np.ndarray
    bbox: np.ndarray | None
    min_version: int

    def axes(self, spec: RegionSpec, max_voxels: int) -> list[np.ndarray]:
        """Axes ``lo + i * step`` up to ``hi`` (inclusive) of the bbox, inside the region."""
        if self.bbox is None:
            lo, hi = spec.lower, spec.upper
        else:
            lo, hi = self.bbox[:3], self.bbox[3:]
            if np.any(lo < spec.lower) or np.any(hi > spec.upper):
                raise Problem(
                    422,
                    f"bbox {self.bbox.tolist()} leaves region {spec.name!r}, whose bounds are "
                    f"{spec.bounds_m.min} .. {spec.bounds_m.max} (ENU metres)",
                )
        try:
            return RegionSpec.box_axes(lo, hi, self.step, max_voxels)
        except ValueError as exc:  # the voxel limit
            raise Problem(422, str(exc)) from None


async def grid_params(
    step: Annotated[str, Query(pattern=STEP, description="dx,dy,dz metres (or one number for all axes)")],
    bbox: Annotated[
        str | None, Query(pattern=BOX3, description="xmin,ymin,zmin,xmax,ymax,zmax in region ENU metres")
    ] = None,
    min_version: MinVersion = 0,
) -> GridParams:
    box = None if bbox is None else _floats(bbox, 6, "bbox")
    if box is not None and np.any(box[3:] < box[:3]):
        raise Problem(422, f"bbox max {box[3:].tolist()} must not be below its min {box[:3].tolist()}")
    return GridParams(_floats(step, 3, "step"), box, min_version)


GridDep = Annotated[GridParams, Depends(grid_params)]


#: Work (points or voxels x the map's posteriors) a light read does on the event loop itself
#: (:mod:`service.lanes`); more goes on in a light thread. 10,000: a 1,000-point query of 8
#: sectors, about 5.5 ms here (``bench/bench_service.py``'s library rows)
INLINE_COST = 10_000


def _light_or_heavy(svc: Service, info: RegionInfo, min_version: int, rows: int, work):
    """``work()`` now if it is light (``rows`` points or voxels times the map's posteriors
    within ``light_cost``; in a light thread if it runs on the event loop and costs more than
    :data:`INLINE_COST`), else handed on to the heavy lane; first, if no map of at least
    ``min_version`` is ready, a wait for it (no lane's thread holds it)."""
    maps = svc.maps
    if not maps.ready(info, min_version):
        return Waiting(
            lambda: maps.wait_for(info, min_version),
            lambda: _light_or_heavy(svc, info, min_version, rows, work),
        )
    cost = rows * info.spec.posteriors
    if cost > svc.settings.light_cost:
        return Heavy(work)
    return Threaded(work) if cost > INLINE_COST and lanes.on_loop() else work()


def _within_budget(svc: Service, spec: RegionSpec, rows: int, modes: bool, media: str, what: str) -> None:
    """422 unless the answer of ``rows`` points or voxels (every class's too with
    ``modes``) fits the memory one request may take, before any work."""
    need = formats.answer_bytes(rows, spec.sectors.classes, modes, media)
    budget = svc.settings.request_memory_mb * 2**20
    if need > budget:
        classes = f" x {spec.sectors.classes} traffic classes" if modes else ""
        raise Problem(
            422,
            f"{rows} {what}{classes} as {media} takes about {need / 2**20:.0f} MiB to answer, more than "
            f"the {budget / 2**20:.0f} MiB one request may take: ask for fewer {what}"
            + (", without modes" if modes else "")
            + ("" if media != JSON else f", or as {ARROW}"),
        )


router = APIRouter(prefix="/v1")


@router.post(
    "/regions",
    status_code=201,
    response_model=RegionView,
    **scoped("admin", **_body_doc(RegionSpec, binary=())),
)
async def create_region(request: Request, svc: ServiceDep):
    """Create a region from its spec; 409 if the name exists. The body is read after the
    token is checked (a parameter would have it parsed first, by anyone)."""
    body = await request.body()
    if formats.media_type(request.headers.get("content-type")) not in (JSON, ""):
        raise Problem(415, f"send the region spec as {JSON}")
    spec = RegionSpec.model_validate_json(formats.json_body(body, svc.limits(0)))
    if spec.directions_scores is not None:
        raise Problem(422, 'directions_scores are written by the fits of a region of "auto" directions')
    budget = svc.settings.map_memory_mb * 2**20
    if spec.map_bytes > budget:
        raise Problem(
            422,
            f"computing this region's map may take {spec.map_bytes / 2**20:.0f} MiB ({spec.couplings:.3g} "
            f"couplings), more than this service's {budget / 2**20:.0f} MiB for one map: raise the spacing "
            "or gamma, or take fewer (model_)directions"
            + (
                f' (of "auto", a fit may choose {max(sectors.AUTO_DIRECTIONS)}: name a count)'
                if spec.directions == "auto"
                else ""
            ),
        )
    info = await svc.run(lambda: svc.maps.store.create_region(spec), write=True)
    return JSONResponse(_view(info), status_code=201)


@router.get("/regions", response_model=list[RegionView], **scoped("read"))
async def list_regions(svc: ServiceDep):
    return await svc.run(lambda: [_view(info) for info in svc.maps.store.list_regions()])


@router.get("/regions/{name}", response_model=RegionView, **scoped("read"))
async def get_region(name: RegionName, svc: ServiceDep):
    return await svc.run(lambda: _view(svc.maps.store.region(name)))


@router.delete("/regions/{name}", status_code=204, **scoped("admin"))
async def delete_region(name: RegionName, svc: ServiceDep):
    await svc.run(lambda: svc.maps.store.delete_region(name), write=True)
    return Response(status_code=204)


IdempotencyKey = Annotated[
    str,
    Header(
        alias=wire.IDEMPOTENCY_HEADER,
        min_length=1,
        max_length=200,
        pattern=r"^[ -~]+$",
        description="the upload's id (printable ASCII): a retry with the same key applies once",
    ),
]


@router.post(
    "/regions/{name}/observations",
    response_model=UploadView,
    **scoped("write", **_body_doc(formats.ObservationsBody, (ARROW, PARQUET), OBSERVATION_COLUMNS)),
)
async def post_observations(name: RegionName, request: Request, upload_id: IdempotencyKey, svc: ServiceDep):
    """Add observations to the map (exactly once per Idempotency-Key)."""
    body = await request.body()

    def work():
        _, obs = _observations(svc, name, body, request.headers.get("content-type"))
        return _apply(svc, name, upload_id, obs)

    return await svc.run(work, heavy=_heavy_body(svc, body), write=True)


def _heavy_body(svc: Service, body: bytes) -> bool:
    """An upload whose body is larger than ``light_body_mb`` decodes and learns in the
    heavy lane."""
    return len(body) > svc.settings.light_body_mb * 2**20


def _observations(svc: Service, name: str, body: bytes, content_type: str | None):
    """The region's spec and the body's observations, checked against it."""
    spec = svc.maps.store.region(name).spec
    obs = formats.read_observations(
        spec, body, formats.media_type(content_type), svc.limits(svc.settings.max_points)
    )
    return spec, obs


def _apply(svc: Service, name: str, upload_id: str, obs: formats.UploadRows, retract=False, **kw) -> dict:
    """Upload (or, with ``replace=True``, fit; with ``retract``, retract) and count it in
    the metrics."""
    maps = svc.maps
    result = (maps.retract if retract else maps.upload)(
        name,
        upload_id,
        obs.X,
        obs.V,
        input_noise_std=obs.input_noise_std,
        sample_weight=obs.sample_weight,
        track=obs.track,
        time=obs.time,
        **kw,
    )
    svc.metrics.upload_applied(result)
    return result


@router.post(
    "/regions/{name}/fit",
    response_model=UploadView,
    **scoped(
        "write",
        **_body_doc(formats.ObservationsBody, (ARROW, PARQUET), OBSERVATION_COLUMNS),
        responses={202: {"model": JobView, "description": "a large fit runs as a job"}},
    ),
)
async def post_fit(name: RegionName, request: Request, upload_id: IdempotencyKey, svc: ServiceDep):
    """Replace the map with this data. Large bodies run as a job (202); the old map keeps
    answering queries until the new one commits."""
    body = await request.body()
    content_type = request.headers.get("content-type")
    spec, obs = await svc.run(
        lambda: _observations(svc, name, body, content_type), _heavy_body(svc, body), body_bytes=len(body)
    )

    def fit(progress=None):
        return _apply(svc, name, upload_id, obs, replace=True, progress=progress)

    settings = svc.settings
    search = spec.grid.size * spec.fit_classes  # a fit's cost grows with it, whatever the rows
    if len(obs.X) <= settings.fit_job_points and search <= settings.fit_job_hinges:
        return await svc.run(fit, heavy=True)
    rows = (obs.X, obs.V, obs.input_noise_std, obs.sample_weight, obs.track, obs.time)
    digest = upload_digest(upload_kind(True), *rows)
    # a fit already stored under this key replays (or, with other rows, is a 409) at once
    stored = await svc.run(lambda: svc.maps.store.upload_result(name, upload_id, digest))
    if stored is not None:
        return stored
    job = svc.jobs.submit(name, upload_id, digest, fit)
    return JSONResponse(job.public(), status_code=202, headers={"Location": f"/v1/jobs/{job.id}"})


@router.post(
    "/regions/{name}/retractions",
    response_model=UploadView,
    **scoped("admin", **_body_doc(formats.ObservationsBody, (ARROW, PARQUET), OBSERVATION_COLUMNS)),
)
async def post_retraction(name: RegionName, request: Request, upload_id: IdempotencyKey, svc: ServiceDep):
    """Retract an acknowledged upload exactly (a sensor found broken): the Idempotency-Key
    names the upload, the body holds the very rows it sent (checked against the ledger's
    digest). The map becomes the map without them; once per upload, a retry replays."""
    body = await request.body()

    def work():
        _, obs = _observations(svc, name, body, request.headers.get("content-type"))
        return _apply(svc, name, upload_id, obs, retract=True)

    return await svc.run(work, heavy=_heavy_body(svc, body), write=True)


@router.post("/regions/{name}/hyperparameters", response_model=RegionView, **scoped("write"))
async def post_hyperparameters(name: RegionName, svc: ServiceDep):
    """The region's settled map at its current version (the background refresh settles it
    too, when no newer version waits): its "auto" alpha and beta at the evidence maximum of
    all its data, recorded in the region view, which this answers. It waits for the refresh, until the
    request's deadline (503 past it; the refresh goes on, and a retry finds its map)."""
    return await svc.run(lambda: _view(svc.maps.fit_hyperparameters(name)), heavy=True)


@router.get("/jobs/{job_id}", response_model=JobView, **scoped("write"))
async def get_job(job_id: Annotated[str, Path(pattern=r"^[0-9a-f]{32}$")], svc: ServiceDep):
    job = svc.jobs.get(job_id)
    if job is None:
        raise Problem(404, f"no job {job_id!r} on this server (jobs are kept in memory per replica)")
    return job.public()


@router.post(
    "/regions/{name}/query",
    response_model=formats.QueryResult,
    **scoped(
        "read", responses={200: {"content": {ARROW: {}}}}, **_body_doc(formats.QueryBody, binary=(ARROW,))
    ),
)
async def query(
    name: RegionName,
    request: Request,
    svc: ServiceDep,
    answer: AnswerDep,
    min_version: MinVersion = 0,
    modes: WithModes = False,
):
    """Predictive mean and std at points; Arrow in and out on request. A point outside the
    region is answered null (``known`` false; counted in ``outside`` and
    ``X-Points-Outside``); every point outside is a 422. A directional region answers its
    mixture, the mode of a heading (``heading_deg``: JSON field or Arrow column), and on
    request (``modes``) every traffic class: JSON ``modes``, or Arrow columns ``share{c}``,
    ``mode{c}_v{e,n,u}``, ``mode{c}_std_{e,n,u}`` and ``share_std``."""
    answer.body = await request.body()
    out = formats.negotiate(request.headers.get("accept"), [JSON, ARROW])
    media = formats.media_type(request.headers.get("content-type"))

    def step():
        info, not_modified = answer.region_or_304(name)
        if not_modified:
            return not_modified
        limits = svc.limits(svc.settings.max_query_points)
        q = formats.read_query(info.spec, answer.body, media, limits, modes)
        _within_budget(svc, info.spec, len(q.X), q.modes, out, "points")

        def work():
            inside = q.inside
            pred = svc.maps.predict(
                name, inside.X, info, min_version, heading_deg=inside.heading_deg, modes=inside.modes
            )
            return formats.encode_points(out, info.spec, pred, answer.headers(pred), q.outside)

        return _light_or_heavy(svc, info, min_version, len(q.X), work)

    return await svc.run(step, body_bytes=len(answer.body))


@router.post(
    "/regions/{name}/routes/assess",
    response_model=formats.AssessResult,
    **scoped(
        "read",
        responses={200: {"content": {JSON: {}}}},
        **_body_doc(formats.RouteBody, binary=()),
    ),
)
async def assess_route(
    name: RegionName, request: Request, svc: ServiceDep, answer: AnswerDep, min_version: MinVersion = 0
):
    """A route of any planner against the map: per segment and in total, the max and mean
    std (of the mode of the heading flown on a directional map), the fraction inside the
    tube ``max_std_mps``, the integrated risk, the conflict exposure and the flow mismatch,
    and whether the vehicle's envelope holds (:mod:`bdf.region.route`). JSON, or GeoJSON: a
    LineString Feature ([lon, lat, alt_m]) with ``times_s``, ``heading_deg``, ``max_std_mps``
    and ``vehicle`` in its properties."""
    answer.body = await request.body()
    media = formats.media_type(request.headers.get("content-type"))

    def step():
        info, not_modified = answer.region_or_304(name)
        if not_modified:
            return not_modified
        route = formats.read_route(info.spec, answer.body, media, svc.limits(MAX_ROUTE_POINTS))
        cost = _route_cost(svc, route)
        # in memory at once: a chunk of samples with every class's mode, and the answer per segment
        _within_budget(svc, info.spec, CHUNK_SAMPLES + len(route.P), True, JSON, "route samples")

        def work():
            got = svc.maps.assess(name, route, info, min_version)
            content = {**got.result, "region_version": got.version}
            return JSONResponse(content, headers=answer.headers(got))

        return _light_or_heavy(svc, info, min_version, cost, work)

    return await svc.run(step, body_bytes=len(answer.body))


def _route_cost(svc: Service, route: formats.RouteQuery) -> int:
    """What assessing ``route`` costs, in map samples (as many query points), before any
    work: its samples on the map and its envelope's (each about
    :data:`ENVELOPE_SAMPLES_PER_POINT` times cheaper); 422 beyond a query's points. Memory
    is a chunk's whatever the route (:func:`bdf.region.route.assess`)."""
    on_map, on_envelope = route_samples(route.P, route.vehicle)
    cost = on_map + on_envelope // ENVELOPE_SAMPLES_PER_POINT
    limit = svc.settings.max_query_points
    if cost > limit:
        km = float(np.linalg.norm(np.diff(route.P, axis=0), axis=1).sum()) / 1e3
        raise Problem(
            422,
            f"a route of {km:.4g} km is read at {on_map} samples on the map (every {SAMPLE_M:g} m) and "
            f"{on_envelope} for the vehicle's envelope, together as costly as {cost} query points, more "
            f"than the {limit} one request may read: assess it in shorter parts",
        )
    return cost


def _on_grid(
    svc: Service, answer: MapAnswer, name: str, axes_of, min_version: int, modes: bool, media: str, encode
):
    """The light step of an answer on a grid: the region (or a 304), its axes
    (``axes_of(spec)``) and the memory budget; then ``encode(spec, axes, prediction)``, now or
    in the heavy lane."""

    def light():
        info, not_modified = answer.region_or_304(name)
        if not_modified:
            return not_modified
        axes = axes_of(info.spec)
        voxels = int(np.prod([len(a) for a in axes]))
        _within_budget(svc, info.spec, voxels, modes, media, "voxels")

        def work():
            pred = svc.maps.predict_grid(name, axes, info, min_version, modes=modes)
            return encode(info.spec, axes, pred)

        return _light_or_heavy(svc, info, min_version, voxels, work)

    return light


@router.get(
    "/regions/{name}/grid",
    **scoped("read", responses={200: {"content": {NPZ: {}, ARROW: {}}}}),
)
async def grid(
    name: RegionName,
    request: Request,
    svc: ServiceDep,
    answer: AnswerDep,
    params: GridDep,
    modes: WithModes = False,
):
    """Mean and std on the voxel grid ``bbox`` x ``step``: npz (arrays mean, std (nx, ny, nz,
    3), known (nx, ny, nz), x, y, z; with ``modes``: share (nx, ny, nz, C), share_std,
    mode_mean and mode_std (nx, ny, nz, C, 3), mode_heading_noise (nx, ny, nz, C, 3: the noise
    variance within mode_std^2 that a known heading narrows, :func:`bdf.sectors.heading_mode`),
    mode_prior_only (nx, ny, nz, C: no data of
    the class within the kernel's reach, the mode is its prior), heading_deg (C,), NaN for
    the slow class),
    Arrow (one row per voxel, C order; ``shape`` in the schema metadata), or JSON for small
    grids."""
    out = formats.negotiate(request.headers.get("accept"), [JSON, NPZ, ARROW])
    if modes and out != NPZ:
        raise Problem(422, f"modes on a grid come as npz: ask for Accept: {NPZ}")
    max_json = svc.settings.max_json_voxels

    def encode(spec, axes, pred):
        return formats.encode_grid(out, spec, axes, pred, answer.headers(pred), max_json)

    axes_of = functools.partial(params.axes, max_voxels=svc.settings.max_grid_voxels)
    return await svc.run(_on_grid(svc, answer, name, axes_of, params.min_version, modes, out, encode))


@router.get(
    "/regions/{name}/tubes",
    **scoped("read", responses={200: {"content": {GEOJSON: {}, NPZ: {}, ARROW: {}}}}),
)
async def tubes(
    name: RegionName,
    request: Request,
    svc: ServiceDep,
    answer: AnswerDep,
    params: GridDep,
    max_std_mps: Annotated[
        float, Query(gt=0, allow_inf_nan=False, description="the tube bound on the predictive std, m/s")
    ],
    component: Annotated[Literal["all", "e", "n", "u"], Query(description="whose std is bounded")] = "all",
    heading_deg: Annotated[
        float | None,
        Query(
            allow_inf_nan=False,
            description="the directional tube: the mode of traffic flying this heading (degrees from "
            "north, clockwise) and where its share is at least min_share",
        ),
    ] = None,
    min_share: Annotated[
        float, Query(ge=0, le=1, description="with heading_deg: the least share")
    ] = sectors.MIN_SHARE,
):
    """The voxels whose predictive std is below ``max_std_mps`` (all components, or one),
    where data lies within the kernel's reach, with their mean velocity: GeoJSON points (lon, lat, alt),
    npz (points, mean, std (k, 3), mask (nx, ny, nz), x, y, z) or Arrow. With ``heading_deg``,
    mean and std are the mode of that heading (its two nearest sectors' modes pooled,
    :func:`bdf.sectors.heading_mode`), and its share, pooled alike, bounds the tube too."""
    out = formats.negotiate(request.headers.get("accept"), [GEOJSON, JSON, NPZ, ARROW])
    bound = formats.TubeBound(max_std_mps, component, heading_deg, min_share)
    max_json = svc.settings.max_json_voxels

    def encode(spec, axes, pred):
        return formats.encode_tube(out, spec, axes, pred, bound, answer.headers(pred), max_json)

    axes_of = functools.partial(params.axes, max_voxels=svc.settings.max_grid_voxels)
    modes = heading_deg is not None
    return await svc.run(_on_grid(svc, answer, name, axes_of, params.min_version, modes, out, encode))


@router.get(
    "/regions/{name}/slice.png",
    response_class=Response,
    **scoped("read", responses={200: {"content": {PNG: {}}}}),
)
async def slice_png(
    name: RegionName,
    svc: ServiceDep,
    answer: AnswerDep,
    alt_m: Annotated[
        float, Query(allow_inf_nan=False, description="altitude of the slice, region ENU metres")
    ],
    layer: Annotated[slices.Layer, Query(description="mean, std, or the tube's mean")] = "mean",
    component: Annotated[slices.Component, Query(description="velocity component shown")] = "e",
    max_std_mps: Annotated[
        float, Query(gt=0, allow_inf_nan=False, description="tube bound (layer=tube), m/s")
    ] = 1.0,
    bbox: Annotated[
        str | None,
        Query(pattern=BOX2, description="xmin,ymin,xmax,ymax in region ENU metres"),
    ] = None,
    step: Annotated[
        float | None, Query(gt=0, allow_inf_nan=False, description="horizontal cell size, metres")
    ] = None,
    min_version: MinVersion = 0,
    min_share: Annotated[
        float, Query(ge=0, le=1, description="layer=modes: the least share drawn")
    ] = sectors.MIN_SHARE,
):
    """A PNG of one horizontal slice with its colour scale and units (the viewer's image).
    ``modes`` draws each traffic class's arrows, ``share`` the largest class's share."""
    view = slices.SliceView(layer, component, max_std_mps, min_share)
    box = None if bbox is None else tuple(_floats(bbox, 4, "bbox"))

    def axes_of(spec: RegionSpec):
        if not spec.lower[2] <= alt_m <= spec.upper[2]:
            raise Problem(
                422, f"alt_m {alt_m} is outside region {name!r}'s {spec.lower[2]} .. {spec.upper[2]} m"
            )
        try:
            x, y = slices.slice_axes(spec.lower, spec.upper, spec.spacing_m, box, step)
        except ValueError as exc:  # a bbox or step the slice cannot have
            raise Problem(422, str(exc)) from None
        return [x, y, np.array([alt_m])]

    def encode(spec, axes, pred):
        origin = (spec.origin.lat, spec.origin.lon)
        return formats.encode_slice(name, axes, pred, view, answer.headers(pred), origin)

    with_modes = layer in ("modes", "share")
    light = _on_grid(svc, answer, name, axes_of, min_version, with_modes, PNG, encode)
    return await svc.run(light)


AltitudeM = Annotated[
    float,
    Query(allow_inf_nan=False, ge=-1000, le=30_000, description="altitude above the WGS84 ellipsoid, m"),
]


@router.get(
    "/regions/{name}/tiles/{z}/{x}/{y}.png",
    **scoped("read", responses={200: {"content": {PNG: {}}}}),
)
async def map_tile(
    name: RegionName,
    z: Annotated[int, Path(ge=0, le=webmap.MAX_ZOOM)],
    x: Annotated[int, Path(ge=0)],
    y: Annotated[int, Path(ge=0)],
    svc: ServiceDep,
    answer: AnswerDep,
    alt_m: AltitudeM,
    layer: Annotated[webmap.Layer, Query(description="what the tile colours (webmap.LAYERS)")] = "speed",
    vmax: Annotated[
        float | None,
        Query(gt=0, allow_inf_nan=False, description="top of the colour scale (default per layer)"),
    ] = None,
    min_version: MinVersion = 0,
):
    """A 256 x 256 Web Mercator raster tile (XYZ) of the map at ``alt_m``: horizontal speed,
    std (the largest component), ``known`` or the busiest class's share, on a fixed colour
    scale (0 .. ``vmax``), faded where not known, transparent outside the region. For any
    web map or GIS (QGIS: an XYZ tile layer); cached by ETag like the grids."""
    try:
        webmap.tile_lonlat(z, x, y, 2)
    except ValueError as exc:
        raise Problem(404, str(exc)) from None
    top = vmax or webmap.LAYERS[layer].default_vmax

    def light():
        info, not_modified = answer.region_or_304(name)
        if not_modified:
            return not_modified
        X, inside = webmap.tile_points(info.spec, z, x, y, alt_m)
        if not len(X):  # the tile misses the region: nothing to answer from the map
            empty = webmap.render_tile(layer, inside, np.zeros(0), np.zeros(0), top)
            return Response(empty, media_type=PNG, headers={"Cache-Control": "max-age=3600"})

        def work():
            pred = svc.maps.predict(name, X, info, min_version, modes=layer == "share")
            share = pred.modes.share if pred.modes is not None else None
            value = webmap.values(layer, pred.mean, pred.std, pred.known, share)
            png = webmap.render_tile(layer, inside, value, pred.known, top)
            return Response(png, media_type=PNG, headers=answer.headers(pred))

        return _light_or_heavy(svc, info, min_version, len(X), work)

    return await svc.run(light)


@router.get("/regions/{name}/flows", **scoped("read", responses={200: {"content": {GEOJSON: {}}}}))
async def flows(
    name: RegionName,
    svc: ServiceDep,
    answer: AnswerDep,
    alt_m: AltitudeM,
    step_m: Annotated[
        float, Query(ge=1, allow_inf_nan=False, description="arrows about this far apart, m")
    ] = 2000,
    min_share: Annotated[
        float, Query(ge=0, le=1, description="the least share of a mode drawn")
    ] = sectors.MIN_SHARE,
    arrow_s: Annotated[
        float, Query(gt=0, le=3600, allow_inf_nan=False, description="an arrow is the flight of this many s")
    ] = 10.0,
    min_version: MinVersion = 0,
):
    """The flows at ``alt_m`` as GeoJSON arrows (MultiLineString: the shaft, the head):
    each traffic class of share at least ``min_share`` at points ``step_m`` apart (one
    class: the mean), as far as it flies in ``arrow_s``; properties speed_mps, heading_deg,
    share, known."""

    def light():
        info, not_modified = answer.region_or_304(name)
        if not_modified:
            return not_modified
        _, _, X, inside = _lattice(svc, info, alt_m, step_m)
        X = X[inside]

        def work():
            pred = svc.maps.predict(name, X, info, min_version, modes=not info.spec.one_class)
            body = webmap.flows_geojson(info.spec, X, pred, min_share, arrow_s)
            return JSONResponse(body, media_type=GEOJSON, headers=answer.headers(pred))

        return _light_or_heavy(svc, info, min_version, len(X), work)

    return await svc.run(light)


def _lattice(svc: Service, info: RegionInfo, alt_m: float, step_m: float):
    """:func:`service.webmap.lattice` of the region at ``alt_m``: 422 when none of it lies
    at that altitude or it holds more than ``max_query_points`` points inside."""
    lon, lat, X, inside = webmap.lattice(info.spec, alt_m, step_m)
    points, most = int(inside.sum()), svc.settings.max_query_points
    if points > most:
        raise Problem(
            422, f"{points} points at step_m {step_m:g} exceed max_query_points {most}: a larger step_m"
        )
    if not points:
        raise Problem(
            422, f"alt_m {alt_m} leaves region {info.spec.name!r}: no point of it lies at that altitude"
        )
    return lon, lat, X, inside


@router.get("/regions/{name}/tube_outline", **scoped("read", responses={200: {"content": {GEOJSON: {}}}}))
async def tube_outline(
    name: RegionName,
    svc: ServiceDep,
    answer: AnswerDep,
    alt_m: AltitudeM,
    max_std_mps: Annotated[float, Query(gt=0, allow_inf_nan=False, description="the tube bound, m/s")],
    step_m: Annotated[float, Query(ge=1, allow_inf_nan=False, description="the lattice contoured, m")] = 500,
    min_version: MinVersion = 0,
):
    """The outline of the velocity tube at ``alt_m``: where every std component is below
    ``max_std_mps``, as GeoJSON contour lines (MultiLineString of [lon, lat]) on a lattice
    ``step_m`` apart; its ``inside`` property is the share of the lattice within the tube."""

    def light():
        info, not_modified = answer.region_or_304(name)
        if not_modified:
            return not_modified
        lon, lat, X, inside = _lattice(svc, info, alt_m, step_m)

        def work():
            pred = svc.maps.predict(name, X[inside], info, min_version)
            body = webmap.tube_outline_geojson(lon, lat, inside, pred.std.max(axis=1), max_std_mps)
            return JSONResponse(body, media_type=GEOJSON, headers=answer.headers(pred))

        return _light_or_heavy(svc, info, min_version, int(inside.sum()), work)

    return await svc.run(light)


@router.get("/regions/{name}/tiles", **scoped("read"))
async def tiles(name: RegionName, svc: ServiceDep):
    """The region's tiles that hold data: key, version, weighted count, points, bytes."""
    return await svc.run(lambda: _tiles(svc.maps.store.snapshot(name, keys=())))


def _tiles(snap) -> dict:
    return {
        "region_version": snap.region.version,
        "tiles": [
            {
                "key": key_str(t.key),
                "version": t.version,
                "count": t.count,
                "points": t.points,
                "bytes": t.nbytes,
                "updated_at": t.updated_at,
            }
            for t in snap.tiles.values()
        ],
    }


ops = APIRouter()


@ops.get("/healthz", **scoped(PUBLIC))
async def healthz():
    """Liveness: the process answers (from the event loop: never behind work)."""
    return {"status": "ok"}


@ops.get("/readyz", **scoped(PUBLIC))
async def readyz(request: Request, svc: ServiceDep):
    """Readiness: the store answers within ``ready_timeout_s``, in a thread of its own (at
    most one check at a time: while one hangs, the next answers 503 at once)."""
    limiter: anyio.CapacityLimiter = request.app.state.ready_limiter
    if limiter.borrowed_tokens:
        raise Problem(503, "the store did not answer the last readiness check yet", {"Retry-After": "1"})
    with anyio.move_on_after(svc.settings.ready_timeout_s) as waited:
        try:
            await anyio.to_thread.run_sync(svc.maps.store.ping, limiter=limiter, abandon_on_cancel=True)
        except Exception as exc:
            raise Problem(
                503, f"the store is unreachable: {type(exc).__name__}", {"Retry-After": "5"}
            ) from exc
    if waited.cancelled_caught:
        raise Problem(
            503,
            f"the store did not answer within {svc.settings.ready_timeout_s:g} s",
            {"Retry-After": "5"},
        )
    return {"status": "ready"}


@ops.get("/viewer", response_class=HTMLResponse, **scoped(PUBLIC))
async def viewer(svc: ServiceDep):
    """The web map: the region's map as raster tiles at an altitude (speed, std, known,
    share) with its legend, flows as arrows, the tube's outline, routes from a GeoJSON
    file, the answer at a click, and the view in the URL; over a basemap if
    ``viewer_basemap_url`` is set. The page itself is public; its requests carry the token
    typed into it, if any."""
    basemap = svc.settings.viewer_basemap_url
    page = VIEWER_HTML.replace("{{BASEMAP}}", html.escape(basemap or "", quote=True))
    page = page.replace("{{LEGENDS}}", json.dumps(webmap.legends()).replace("</", "<\\/"))
    return HTMLResponse(page, headers={"Content-Security-Policy": viewer_policy(basemap)})


@ops.get("/static/{file}", **scoped(PUBLIC))
async def static(file: str):
    """The viewer's MapLibre GL JS files (BSD-3-Clause, its licence beside them)."""
    if file not in STATIC:
        raise Problem(404, f"no static file {file!r}")
    path, media = STATIC[file]
    return FileResponse(path, media_type=media, headers={"Cache-Control": "public, max-age=86400"})


@ops.get(
    "/metrics",
    response_class=Response,
    **scoped(PUBLIC, responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}}),
)
async def metrics(svc: ServiceDep):
    """Prometheus text format: requests and latency per route, lanes, cache, refreshes,
    uploads (from the event loop: it reads counters only, never the store)."""
    return Response(generate_latest(svc.metrics.registry), media_type=CONTENT_TYPE_LATEST)


def create_app(settings: Settings | None = None, store: MapStore | None = None) -> FastAPI:
    """The ASGI app. ``store`` defaults to the one ``settings.store`` names."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        app.state.ready_limiter = anyio.CapacityLimiter(1)
        svc.maps.open()  # a restarted app (tests) refreshes again
        # what is loaded by now lives as long as the process: out of the collector's sight,
        # a full collection (triggered by a large JSON body's lists) scans only what requests
        # made, not the libraries' million objects, which it would scan holding the GIL
        gc.freeze()
        yield
        svc.jobs.shutdown()  # graceful: running fits finish and commit
        svc.maps.store.close()

    app = FastAPI(
        title="bdf-maps",
        version="1",
        description="3D velocity maps with calibrated uncertainty, tiled per region.",
        lifespan=lifespan,
        # the service's own metrics are Prometheus' (/metrics); FastAPI's OpenTelemetry hooks
        # would look up three providers on every request, for nobody
        telemetry={"tracing": False, "metrics": False, "logs": False},
    )
    maps = RegionMaps(
        store or open_store(settings.store, settings.store_timeout_s),
        cache_mb=settings.cache_mb,
        isolate=True,
    )
    work_lanes = Lanes(
        settings.threads,
        settings.queue,
        settings.heavy_threads,
        settings.heavy_queue,
        settings.max_waiting,
        inline=maps.store.local_reads,
    )
    svc = app.state.service = Service(settings, maps, Jobs(), work_lanes, Metrics(maps, work_lanes))
    problems.install(app, PATTERNS)
    if settings.cors_origins:  # off unless configured: browsers on other origins get no access
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=[
                "Authorization",
                "Content-Type",
                "Accept",
                wire.IDEMPOTENCY_HEADER,
                "If-None-Match",
            ],
            expose_headers=[
                "ETag",
                wire.VERSION_HEADER,
                wire.VERSIONS_BEHIND_HEADER,
                wire.SECONDS_BEHIND_HEADER,
                wire.REFRESHES_BEHIND_HEADER,
                wire.EVIDENCE_GAP_HEADER,
                wire.REQUEST_ID_HEADER,
                "Location",
                "Retry-After",
            ],
        )
    app.add_middleware(
        RequestMiddleware,
        max_body_bytes=int(settings.max_body_mb * 2**20),
        metrics=svc.metrics,
        timeout_s=settings.request_timeout_s,
    )
    app.include_router(router)
    app.include_router(ops)
    return app
