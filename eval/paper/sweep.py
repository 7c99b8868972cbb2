"""Sweeps on Dask: every job is a task, every finished job a file in a result store.

A job is a JSON-able mapping (its *spec*: what to run, e.g. dataset, detector, parameters, seed).
``ResultStore`` keeps one file per finished job, named by the SHA-256 of the canonical JSON of its
spec, written atomically (temporary file, then ``os.replace``), so a sweep that is interrupted at
any moment leaves only complete results, and rerunning it skips every job whose file exists.
Changing anything in a spec changes its key, so stale results are never reused.

``run_jobs`` submits the missing jobs to a ``dask.distributed`` client and stores each result as it
arrives (on the machine that runs the sweep, so remote workers need no access to the store). A job
that raises, or whose worker dies, is reported with its error and traceback and does not stop the
others; it gets no file, so the next run retries it.

``dask_client``: a ``LocalCluster`` of one single-threaded worker process per core (OpenCV and BLAS
limited to one thread per worker, so workers do not compete for cores) unless ``scheduler`` gives
the address of a running cluster (``dask scheduler`` / ``dask worker ADDRESS``). Jobs that write
files besides their result (pipeline runs) need a folder all workers can reach. The LocalCluster
listens on 127.0.0.1 only (scheduler, nanny, workers and their HTTP endpoints) and serves no
dashboard unless ``ClusterOptions.dashboard`` asks for one (``--dashboard ADDRESS``).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import re
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from frontends.errors import ConfigError, InputFileError

JobSpec = Mapping[str, Any]
JobResult = dict[str, Any]

#: Environment of local worker processes: one thread per worker for every numeric library.
SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: The only interface a LocalCluster listens on, unless a dashboard address says otherwise.
LOCALHOST = "127.0.0.1"
_DASHBOARD_ADDRESS = re.compile(r"(?P<host>[^\s:,]*):(?P<port>[0-9]{1,5})")


def job_key(spec: JobSpec) -> str:
    """A stable key of a job: SHA-256 (first 20 hex digits) of its canonical JSON."""
    canonical = json.dumps(spec, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()[:20]


def write_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and ``os.replace``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as stream:
            stream.write(text)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


class ResultStore:
    """One JSON file per finished job under ``root``, keyed by ``job_key`` of its spec."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def path(self, spec: JobSpec) -> Path:
        return self.root / f"{job_key(spec)}.json"

    def has(self, spec: JobSpec) -> bool:
        return self.path(spec).is_file()

    def load(self, spec: JobSpec) -> JobResult:
        path = self.path(spec)
        try:
            stored = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputFileError(
                path, f"unreadable result file ({exc}); delete it to rerun the job"
            ) from None
        return dict(stored["result"])

    def save(self, spec: JobSpec, result: JobResult) -> None:
        write_atomically(self.path(spec), json.dumps({"spec": spec, "result": result}, indent=1) + "\n")


@dataclass(frozen=True)
class JobFailure:
    spec: JobSpec
    error: str
    traceback: str


@dataclass
class SweepOutcome:
    #: Result of every job that has one (stored now or before), by job key, in submission order.
    results: dict[str, JobResult] = field(default_factory=dict)
    failures: list[JobFailure] = field(default_factory=list)
    executed: int = 0
    reused: int = 0
    seconds: float = 0.0

    def result(self, spec: JobSpec) -> JobResult | None:
        return self.results.get(job_key(spec))


@dataclass(frozen=True)
class ClusterOptions:
    #: Address of a running Dask scheduler; None: a LocalCluster on this machine.
    scheduler: str | None = None
    #: Local workers; None: one per core.
    workers: int | None = None
    #: Local workers as processes (True) or threads of this process (False, for tests).
    processes: bool = True
    #: Where the local Dask dashboard listens, ``HOST:PORT`` (``:PORT``: every interface, port 0: any
    #: free port); None: no dashboard. Not for ``scheduler``, which serves its own.
    dashboard: str | None = None

    def __post_init__(self) -> None:
        if self.dashboard is None:
            return
        if self.scheduler:
            raise ConfigError(
                "--dashboard applies to the local cluster only; the scheduler at --scheduler serves its own"
            )
        match = _DASHBOARD_ADDRESS.fullmatch(self.dashboard)
        if match is None or int(match["port"]) > 65535:
            shown = self.dashboard if len(self.dashboard) <= 60 else self.dashboard[:60] + "..."
            raise ConfigError(f"--dashboard {shown!r}: expected HOST:PORT or :PORT (e.g. 127.0.0.1:8787)")


def limit_threads() -> None:
    """Run on each local worker: OpenCV single-threaded (its pool ignores OMP_NUM_THREADS)."""
    import cv2

    cv2.setNumThreads(1)


@contextmanager
def dask_client(options: ClusterOptions) -> Iterator[Any]:
    from dask.distributed import Client, LocalCluster

    if options.scheduler:
        with Client(options.scheduler) as client:
            yield client
        return
    workers = options.workers or os.cpu_count() or 1
    extra: dict[str, Any] = {"env": SINGLE_THREAD_ENV} if options.processes else {}
    try:
        cluster = LocalCluster(
            n_workers=workers,
            threads_per_worker=1,
            processes=options.processes,
            # tcp even for threads: with inproc:// Dask's HTTP endpoints have no host to copy and bind
            # every interface. The scheduler always runs an HTTP server (health, metrics); without a
            # dashboard it gets a free port on localhost rather than 8787.
            host=LOCALHOST,
            protocol="tcp://",
            dashboard_address=options.dashboard or f"{LOCALHOST}:0",
            scheduler_kwargs={"dashboard": options.dashboard is not None},
            **extra,
        )
    except (OSError, RuntimeError) as exc:
        # A dashboard host that does not resolve or is not this machine's fails inside Dask's start-up.
        cause = exc if isinstance(exc, OSError) else exc.__cause__
        if options.dashboard is None or not isinstance(cause, OSError):
            raise
        raise ConfigError(f"--dashboard {options.dashboard}: cannot listen there ({cause})") from None
    with cluster, Client(cluster) as client:
        if options.dashboard is not None:
            everywhere = " (listening on every interface)" if options.dashboard.startswith(":") else ""
            print(f"Dask dashboard: {cluster.dashboard_link}{everywhere}", flush=True)
            if importlib.util.find_spec("bokeh") is None:
                print("note: bokeh is not installed, so the dashboard only says to install it", flush=True)
        if options.processes:
            client.run(limit_threads)
        yield client


def run_jobs(
    client: Any,
    specs: Sequence[JobSpec],
    execute: Callable[[JobSpec], JobResult],
    store: ResultStore,
    on_result: Callable[[JobSpec, JobResult], None] | None = None,
) -> SweepOutcome:
    """Run every spec without a stored result on ``client``; store each result as it arrives."""
    from dask.distributed import as_completed

    start = time.perf_counter()
    outcome = SweepOutcome()
    unique = {job_key(spec): spec for spec in specs}
    pending: dict[Any, JobSpec] = {}
    for key, spec in unique.items():
        if store.has(spec):
            outcome.results[key] = store.load(spec)
            outcome.reused += 1
        else:
            pending[client.submit(execute, spec, key=f"job-{key}", pure=False)] = spec
    finished: dict[str, JobResult] = {}
    for future in as_completed(list(pending)):
        spec = pending[future]
        if future.status == "error":
            error = future.exception()
            outcome.failures.append(JobFailure(spec, f"{type(error).__name__}: {error}", _traceback(future)))
            continue
        result = future.result()
        store.save(spec, result)
        finished[job_key(spec)] = result
        outcome.executed += 1
        if on_result is not None:
            on_result(spec, result)
    # Submission order, whatever order the jobs finished in.
    available = {**outcome.results, **finished}
    outcome.results = {key: available[key] for key in unique if key in available}
    outcome.seconds = time.perf_counter() - start
    return outcome


def _traceback(future: Any) -> str:
    import traceback

    trace = future.traceback()
    return "".join(traceback.format_tb(trace)) if trace is not None else ""
