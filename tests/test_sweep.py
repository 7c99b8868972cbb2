"""The sweep engine: hashed result store, resume without recomputation, failing jobs isolated (Dask)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from eval.paper.sweep import ClusterOptions, ResultStore, dask_client, job_key, run_jobs

THREADS = ClusterOptions(workers=2, processes=False)


def square(spec: Any) -> dict[str, Any]:
    """A toy job: counts its executions in a file named by the spec, fails for x == 3."""
    with open(spec["counter"], "a", encoding="utf-8") as handle:
        handle.write(f"{spec['x']}\n")
    if spec["x"] == 3:
        raise ValueError("x = 3 is not allowed")
    return {"value": spec["x"] ** 2}


def executions(counter: Path) -> list[int]:
    return sorted(int(line) for line in counter.read_text(encoding="utf-8").split())


def test_job_key_is_canonical_and_sensitive() -> None:
    assert job_key({"a": 1, "b": [1, 2]}) == job_key({"b": [1, 2], "a": 1})
    assert job_key({"a": 1}) != job_key({"a": 2})
    assert len(job_key({"a": 1})) == 20


def test_store_writes_atomically_and_reads_back(tmp_path: Path) -> None:
    store = ResultStore(tmp_path / "results")
    spec = {"kind": "toy", "x": 1}
    assert not store.has(spec)
    store.save(spec, {"value": 1.5})
    assert store.has(spec)
    assert store.load(spec) == {"value": 1.5}
    # One file named by the key, with the spec beside the result; no temporary files left.
    files = list((tmp_path / "results").iterdir())
    assert [f.name for f in files] == [f"{job_key(spec)}.json"]
    assert json.loads(files[0].read_text())["spec"] == spec


def test_failing_job_is_reported_and_the_others_finish(tmp_path: Path) -> None:
    counter = tmp_path / "count.txt"
    specs = [{"x": x, "counter": str(counter)} for x in range(6)]
    store = ResultStore(tmp_path / "results")
    with dask_client(THREADS) as client:
        outcome = run_jobs(client, specs, square, store)
    assert outcome.executed == 5 and outcome.reused == 0
    assert len(outcome.failures) == 1
    failure = outcome.failures[0]
    assert failure.spec["x"] == 3
    assert failure.error == "ValueError: x = 3 is not allowed"
    assert "square" in failure.traceback
    assert [outcome.result(s) for s in specs] == [{"value": x * x} for x in (0, 1, 2)] + [None] + [
        {"value": 16},
        {"value": 25},
    ]
    assert not store.has(specs[3])


def test_interrupted_sweep_resumes_without_redoing_finished_jobs(tmp_path: Path) -> None:
    counter = tmp_path / "count.txt"
    specs = [{"x": x, "counter": str(counter)} for x in (0, 1, 2, 4, 5, 6, 7)]
    store = ResultStore(tmp_path / "results")
    with dask_client(THREADS) as client:
        # The interrupted run: only the first three jobs got their results stored.
        first = run_jobs(client, specs[:3], square, store)
        mtimes = {p.name: p.stat().st_mtime_ns for p in store.root.iterdir()}
        resumed = run_jobs(client, specs, square, store)
        again = run_jobs(client, specs, square, store)
    assert first.executed == 3
    assert (resumed.executed, resumed.reused) == (4, 3)
    assert (again.executed, again.reused) == (0, 7)
    # Every job ran exactly once over the three runs, and the finished files were not rewritten.
    assert executions(counter) == [0, 1, 2, 4, 5, 6, 7]
    assert {p.name: p.stat().st_mtime_ns for p in store.root.iterdir() if p.name in mtimes} == mtimes
    # The resumed sweep's results equal a fresh, uninterrupted sweep's, in submission order.
    with dask_client(THREADS) as client:
        fresh = run_jobs(client, specs, square, ResultStore(tmp_path / "fresh"))
    assert list(resumed.results.values()) == list(fresh.results.values()) == list(again.results.values())
    assert [r["value"] for r in resumed.results.values()] == [0, 1, 4, 16, 25, 36, 49]


def test_unreadable_result_file_names_the_file(tmp_path: Path) -> None:
    from frontends.errors import InputFileError

    store = ResultStore(tmp_path)
    spec = {"x": 1}
    store.path(spec).write_text("{truncated", encoding="utf-8")
    with pytest.raises(InputFileError, match=job_key(spec)):
        store.load(spec)


def test_existing_scheduler_by_address(tmp_path: Path) -> None:
    counter = tmp_path / "count.txt"
    specs = [{"x": x, "counter": str(counter)} for x in (1, 2)]
    # Not a LocalCluster with a dashboard: without bokeh, Dask then adds its "install bokeh" page to
    # every later scheduler of this process (it appends to its config list), and the tests below see it.
    with dask_client(ClusterOptions(workers=1, processes=False)) as cluster:
        with dask_client(ClusterOptions(scheduler=cluster.scheduler.address)) as client:
            outcome = run_jobs(client, specs, square, ResultStore(tmp_path / "results"))
        assert len(cluster.scheduler_info()["workers"]) == 1
    assert [r["value"] for r in outcome.results.values()] == [1, 4]


def _listening() -> set[tuple[str, int]]:
    """(address, port) of every TCP socket this process and its children listen on."""
    import psutil

    me = psutil.Process()
    sockets = set()
    for process in [me, *me.children(recursive=True)]:
        try:
            connections = process.net_connections(kind="tcp")
        except psutil.NoSuchProcess:
            continue
        sockets |= {(c.laddr.ip, c.laddr.port) for c in connections if c.status == psutil.CONN_LISTEN}
    return sockets


def _serves_dashboard(port: int) -> bool:
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=30):
            return True
    except urllib.error.HTTPError as error:
        if error.code == 404:
            return False
        raise


@pytest.mark.parametrize("processes", [True, False], ids=["processes", "threads"])
def test_local_cluster_listens_on_localhost_only_and_has_no_dashboard(processes: bool) -> None:
    before = _listening()
    with dask_client(ClusterOptions(workers=1, processes=processes)) as client:
        opened = _listening() - before
        http_port = client.scheduler_info()["services"]["dashboard"]
        # Scheduler, worker (and nanny), and the scheduler's health/metrics endpoint: all on localhost.
        assert len(opened) >= 3
        assert {address for address, _ in opened} == {"127.0.0.1"}
        assert ("127.0.0.1", http_port) in opened
        assert not _serves_dashboard(http_port)


def test_dashboard_on_request_listens_where_asked(capsys: pytest.CaptureFixture[str]) -> None:
    import dask
    import distributed  # noqa: F401  (registers the config defaults read below)

    before = _listening()
    # A copy of Dask's route list, which a dashboard without bokeh appends to (see above).
    routes = list(dask.config.get("distributed.scheduler.http.routes"))
    options = ClusterOptions(workers=1, processes=False, dashboard="127.0.0.1:0")
    with dask.config.set({"distributed.scheduler.http.routes": routes}), dask_client(options) as client:
        opened = _listening() - before
        port = client.scheduler_info()["services"]["dashboard"]
        assert {address for address, _ in opened} == {"127.0.0.1"}
        assert ("127.0.0.1", port) in opened
        assert _serves_dashboard(port)
    assert f"Dask dashboard: http://127.0.0.1:{port}/status" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"dashboard": "8787"}, "expected HOST:PORT"),
        ({"dashboard": "localhost:99999"}, "expected HOST:PORT"),
        ({"dashboard": "a:1:2"}, "expected HOST:PORT"),
        ({"dashboard": "x" * 10_000}, r"'x{60}\.\.\.'"),
        ({"dashboard": ":8787", "scheduler": "tcp://10.0.0.1:8786"}, "local cluster only"),
    ],
)
def test_bad_dashboard_option_is_a_config_error(options: dict[str, Any], message: str) -> None:
    from frontends.errors import ConfigError

    with pytest.raises(ConfigError, match=message) as raised:
        ClusterOptions(**options)
    assert len(str(raised.value)) < 200


def test_dashboard_that_cannot_listen_is_a_config_error() -> None:
    from frontends.errors import ConfigError

    # An address of TEST-NET-3 (RFC 5737), which no machine of ours has.
    options = ClusterOptions(workers=1, processes=False, dashboard="203.0.113.1:0")
    with pytest.raises(ConfigError, match=r"203\.0\.113\.1:0: cannot listen there"), dask_client(options):
        pass


@pytest.mark.parametrize("command", ["table", "sweep"])
def test_dashboard_option_of_eval_commands(
    command: str, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from eval.cli import main
    from eval.paper import table

    seen: list[ClusterOptions] = []

    class Started(Exception):
        pass

    def capture(config: Any, out: Path, cluster: ClusterOptions) -> Any:
        seen.append(cluster)
        raise Started

    monkeypatch.setattr(table, "load_experiment_config", lambda *args: None)
    monkeypatch.setattr(table, f"run_{command}", capture)
    common = ["eval", command, "--config", "c.yaml", "--out", str(tmp_path)]
    for extra in ([], ["--dashboard", "127.0.0.1:8787"]):
        with pytest.raises(Started):
            main([*common, *extra])
    assert [options.dashboard for options in seen] == [None, "127.0.0.1:8787"]
