"""The dask runner's resubmission of innocent pairs, with a scripted client instead of a cluster.

A pair whose finished result was lost with a worker that another pair crashed (its future turns
``lost``), or that was running on a worker gctr replaced because another pair timed out, is
resubmitted with the same seed, at most ``MAX_RESUBMITS`` times; a pair that crashes its own worker is
not. On a real cluster the race is rare and timing-dependent (tests/test_dask.py runs the
real thing and did not hit it in 25 logged runs); here every future's fate is scripted, so each path
runs deterministically.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

distributed = pytest.importorskip("distributed")

from gctr_cli import dask_executor  # noqa: E402
from gctr_cli.config import config_from_dict  # noqa: E402
from gctr_cli.manifest import PairSpec  # noqa: E402
from gctr_cli.outcome import PairOutcome, failed_outcome  # noqa: E402


class ScriptedFuture:
    """A dask future whose status (and result or exception) the test chose; ``pending`` until the
    scripted client kills its worker, if it is running."""

    def __init__(self, key: str, status: str, result: Any = None, exception: BaseException | None = None,
                 worker: str | None = None) -> None:
        self.key, self.status, self._result, self._exception = key, status, result, exception
        self.worker = worker

    def result(self) -> Any:
        return self._result

    def exception(self) -> BaseException | None:
        return self._exception

    def done(self) -> bool:
        return self.status != "pending"

    def release(self) -> None:
        pass

    def cancel(self) -> None:
        pass

    def kill(self) -> None:
        """Its worker died while running it: it fails with ``KilledWorker`` naming that worker."""
        self._exception, self.status = killed_on(self.key, str(self.worker)), "error"


def killed_on(key: str, worker: str) -> Exception:
    """The exception of a task whose ``worker`` died while running it."""
    return distributed.KilledWorker(key, SimpleNamespace(address=worker), 0)


class ScriptedClient:
    """Enough of ``distributed.Client`` for :func:`dask_executor.dask_outcomes`: each submission of a
    pair takes the next fate from ``fates[pair_id]`` (default: finished), and every submission is
    recorded as (pair_id, seed). Fates: ``finished``; ``lost``; ``killed:<worker>`` (its worker died
    while running it); ``queued:<worker>`` (its worker died before it started there); ``running:<worker>``
    (starts on the worker and runs until gctr restarts that
    worker, then fails as killed there). Restarted workers are recorded in ``restarted``."""

    status = "running"

    def __init__(self, fates: dict[str, list[str]]) -> None:
        self.fates = {k: list(v) for k, v in fates.items()}
        self.submissions: list[tuple[str, int]] = []
        self.restarted: list[str] = []
        self.running: list[ScriptedFuture] = []
        self.on_start: Any = None

    def submit(self, fn: Any, spec: PairSpec, seed: int, *args: Any, key: str, **kw: Any) -> ScriptedFuture:
        del fn, args, kw
        self.submissions.append((spec.pair_id, seed))
        queue = self.fates.get(spec.pair_id)
        fate = queue.pop(0) if queue else "finished"
        if fate == "finished":
            ran = failed_outcome(spec, seed, f"ran (submission {len(self.submissions)})", "register", 0.0)
            return ScriptedFuture(key, "finished", result=ran)
        if fate == "lost":
            return ScriptedFuture(key, "lost")
        kind, worker = fate.split(":", 1)
        if kind == "killed":  # it started, and its worker died under it
            self.on_start((None, {"key": key, "worker": worker}))
            return ScriptedFuture(key, "error", exception=killed_on(key, worker))
        if kind == "queued":  # it waited on a worker that another pair crashed: it never started
            return ScriptedFuture(key, "error", exception=killed_on(key, worker))
        future = ScriptedFuture(key, "pending", worker=worker)  # "running:<worker>"
        self.running.append(future)
        self.on_start((None, {"key": key, "worker": worker}))  # as run_task announces its start
        return future

    def restart_workers(self, workers: list[str], timeout: float, raise_for_error: bool) -> dict[str, str]:
        """Restart ``workers``: every task still running there fails as killed (the timed-out one
        was cancelled by gctr first and is no longer waited for)."""
        del timeout, raise_for_error
        self.restarted += workers
        for future in self.running:
            if future.status == "pending" and future.worker in workers:
                future.kill()
        return {w: "OK" for w in workers}

    def nthreads(self) -> dict[str, int]:
        return {"tcp://w1": 1}

    def as_current(self) -> contextlib.AbstractContextManager:
        return contextlib.nullcontext()

    def subscribe_topic(self, topic: str, handler: Any) -> None:
        del topic
        self.on_start = handler

    def unsubscribe_topic(self, *a: Any) -> None:
        pass

    def register_plugin(self, *a: Any, **kw: Any) -> None:
        pass

    def close(self, timeout: float = 0) -> None:
        pass


def wait_for_done(futures: list[ScriptedFuture], timeout: float, return_when: str) -> tuple[set, set]:
    """``distributed.wait`` over scripted futures: the done ones, after a short pause if none is."""
    del return_when
    done = {f for f in futures if f.done()}
    if not done:
        time.sleep(min(timeout, 0.005))
    return done, set(futures) - done


def run(monkeypatch: pytest.MonkeyPatch, fates: dict[str, list[str]],
        time_limit_s: float = 600.0) -> tuple[dict[str, PairOutcome], ScriptedClient]:
    """The outcomes of pairs ``a``, ``b`` (seeds 11, 12) under the scripted ``fates``."""
    client = ScriptedClient(fates)
    monkeypatch.setattr(dask_executor, "connect", lambda scheduler, n: (client, None))
    monkeypatch.setattr(distributed, "wait", wait_for_done)
    specs = [PairSpec(pid, Path(f"{pid}_src.ply"), Path(f"{pid}_tgt.ply")) for pid in ("a", "b")]
    config = config_from_dict({}, "<test>")
    outcomes = dask_executor.dask_outcomes([(specs[0], 11), (specs[1], 12)], config, 1, None, time_limit_s,
                                           scheduler="tcp://scripted:8786")
    return {o.pair_id: o for o in outcomes}, client


def test_a_result_lost_with_its_worker_is_resubmitted_with_the_same_seed(monkeypatch):
    out, client = run(monkeypatch, {"a": ["lost", "finished"]})
    assert client.submissions == [("a", 11), ("b", 12), ("a", 11)]
    assert out["a"].message == "ran (submission 3)" and out["a"].seed == 11
    assert out["b"].message == "ran (submission 2)"


def test_resubmission_stops_after_max_resubmits(monkeypatch):
    fates = ["lost"] * (dask_executor.MAX_RESUBMITS + 1)
    out, client = run(monkeypatch, {"a": fates})
    assert [s for s in client.submissions if s[0] == "a"] == [("a", 11)] * (dask_executor.MAX_RESUBMITS + 1)
    assert out["a"].status == "failed" and out["a"].failure == "worker"
    assert out["a"].message == "task lost by the dask cluster"
    assert out["b"].message.startswith("ran")


def test_a_pair_that_kills_its_own_worker_is_not_resubmitted(monkeypatch):
    out, client = run(monkeypatch, {"a": ["killed:tcp://w1"]})
    assert client.submissions == [("a", 11), ("b", 12)]
    assert out["a"].status == "failed" and out["a"].failure == "worker"
    assert "worker died" in out["a"].message and "tcp://w1" in out["a"].message


def test_a_pair_queued_on_a_worker_that_another_pair_crashed_is_resubmitted(monkeypatch):
    # gctr's own LocalCluster sends a worker a second pair while the first runs; a kill -9 of that worker
    # failed both as "worker died" (found by an audit, 3 of 3 runs). The waiting one never started: it runs again.
    out, client = run(monkeypatch, {"a": ["killed:tcp://w1"], "b": ["queued:tcp://w1", "finished"]})
    assert client.submissions == [("a", 11), ("b", 12), ("b", 12)]
    assert out["a"].failure == "worker" and "tcp://w1" in out["a"].message
    assert out["b"].message == "ran (submission 3)" and out["b"].seed == 12
    # the pair that crashed the worker is not known (its start announcement died with it: a crash right
    # after starting): nobody runs again, or that pair would crash another worker, and another (a review
    # saw three workers killed for one pair)
    out, client = run(monkeypatch, {"a": ["queued:tcp://w1"], "b": ["queued:tcp://w1", "finished"]})
    assert client.submissions == [("a", 11), ("b", 12)]
    assert out["a"].failure == "worker" and out["b"].failure == "worker"


def test_a_pair_on_a_worker_replaced_after_another_pairs_time_out_is_resubmitted(monkeypatch):
    # a hangs on w1 past the time limit; gctr restarts w1 (external cluster: through its nanny), which
    # kills b, running there too. b did nothing wrong: it runs again, with its seed.
    out, client = run(monkeypatch, {"a": ["running:tcp://w1"], "b": ["running:tcp://w1", "finished"]},
                      time_limit_s=0.05)
    assert client.restarted == ["tcp://w1"]
    assert client.submissions == [("a", 11), ("b", 12), ("b", 12)]
    assert out["a"].status == "failed" and out["a"].failure == "timeout"
    assert out["a"].message == "timed out after 0.05 s"
    assert out["b"].message == "ran (submission 3)" and out["b"].seed == 12


def test_a_pair_killed_on_a_worker_gctr_did_not_replace_is_not_resubmitted(monkeypatch):
    # the same time-out on w1, but b dies on w2: its own crash, not gctr's restart
    out, client = run(monkeypatch, {"a": ["running:tcp://w1"], "b": ["killed:tcp://w2"]}, time_limit_s=0.05)
    assert client.restarted == ["tcp://w1"]
    assert client.submissions == [("a", 11), ("b", 12)]
    assert out["b"].failure == "worker" and "tcp://w2" in out["b"].message
