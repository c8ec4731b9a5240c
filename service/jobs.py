"""Background fit jobs: large fits run in a worker thread while the old map keeps serving.

Jobs live in the memory of the replica that accepted them (``GET /v1/jobs/{id}`` must
reach the same replica); what they produce is in the store, so a lost job record never
loses data: re-posting the fit with the same Idempotency-Key replays or redoes it.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

from service.lanes import Overloaded
from service.problems import public_detail
from service.store import UploadConflict

log = logging.getLogger("bdf.service")
#: Finished jobs kept for status queries.
KEEP_FINISHED = 1000


@dataclass
class Job:
    id: str
    region: str
    upload_id: str
    digest: str = field(repr=False)
    state: Literal["queued", "running", "succeeded", "failed"] = "queued"
    progress: float = 0.0
    result: dict | None = None
    error: str | None = None
    created_at: float = field(default_factory=time.time)
    finished_at: float | None = None

    def public(self) -> dict:
        out = dataclasses.asdict(self)
        del out["digest"]
        return out


class Jobs:
    """A queue of fit jobs run one at a time (a fit uses the cores it is given), at most
    ``max_queued`` waiting (:class:`service.lanes.Overloaded` beyond)."""

    def __init__(self, max_queued: int = 8):
        self.max_queued = max_queued
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="bdf-fit")
        self._jobs: dict[str, Job] = {}
        self._by_upload: dict[tuple[str, str], str] = {}
        self._lock = threading.Lock()

    def submit(
        self, region: str, upload_id: str, digest: str, work: Callable[[Callable[[float], None]], dict]
    ) -> Job:
        """Queue ``work(progress)`` unless the same (region, upload id) is already queued or
        running: then that job is returned if it holds the same rows (``digest``), else
        :class:`UploadConflict` (as the ledger answers once it is stored)."""
        with self._lock:
            known = self._jobs.get(self._by_upload.get((region, upload_id), ""))
            if known is not None and known.state in ("queued", "running"):
                if known.digest != digest:
                    raise UploadConflict(
                        f"upload id {upload_id!r} names a fit job still {known.state} with different "
                        "data: send other data under another Idempotency-Key"
                    )
                return known
            if sum(j.state == "queued" for j in self._jobs.values()) >= self.max_queued:
                raise Overloaded(f"{self.max_queued} fit jobs are queued already; retry later", 60)
            job = Job(uuid.uuid4().hex, region, upload_id, digest)
            self._jobs[job.id] = job
            self._by_upload[(region, upload_id)] = job.id
            self._forget_old()
        self._pool.submit(self._run, job, work)
        return job

    def get(self, job_id: str) -> Job | None:
        return self._jobs.get(job_id)

    def shutdown(self) -> None:
        """Finish queued and running jobs (graceful shutdown), then stop."""
        self._pool.shutdown(wait=True)

    def _run(self, job: Job, work) -> None:
        job.state = "running"

        def progress(fraction: float) -> None:
            job.progress = round(min(max(fraction, 0.0), 1.0), 4)

        try:
            job.result = work(progress)
            job.state, job.progress = "succeeded", 1.0
        except Exception as exc:  # the job reports what a client may read; the store rolled back
            log.warning("fit job %s for region %s failed: %r", job.id, job.region, exc, exc_info=exc)
            job.state, job.error = "failed", public_detail(exc)
        job.finished_at = time.time()

    def _forget_old(self) -> None:
        finished = [j for j in self._jobs.values() if j.finished_at is not None]
        for job in sorted(finished, key=lambda j: j.finished_at)[: max(0, len(finished) - KEEP_FINISHED)]:
            del self._jobs[job.id]
            self._by_upload.pop((job.region, job.upload_id), None)
