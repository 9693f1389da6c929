"""The dask runner's resubmission of innocent pairs, with a scripted client instead of a cluster.

A pair whose finished result was lost with a worker that another pair crashed (its future turns
``lost``) is resubmitted with the same seed, at most ``MAX_RESUBMITS`` times; a pair that crashes its
own worker is not. On a real cluster the race is rare and timing-dependent (tests/test_dask.py runs the
real thing and did not hit it in 25 logged runs); here every future's fate is scripted, so each path
runs deterministically.
"""

from __future__ import annotations

import contextlib
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
    """A completed dask future whose status (and result or exception) the test chose."""

    def __init__(self, key: str, status: str, result: Any = None, exception: BaseException | None = None) -> None:
        self.key, self.status, self._result, self._exception = key, status, result, exception

    def result(self) -> Any:
        return self._result

    def exception(self) -> BaseException | None:
        return self._exception

    def done(self) -> bool:
        return True

    def release(self) -> None:
        pass

    def cancel(self) -> None:
        pass


class ScriptedClient:
    """Enough of ``distributed.Client`` for :func:`dask_executor.dask_outcomes`: each submission of a
    pair takes the next fate from ``fates[pair_id]`` (default: finished), and every submission is
    recorded as (pair_id, seed)."""

    status = "running"

    def __init__(self, fates: dict[str, list[str]]) -> None:
        self.fates = {k: list(v) for k, v in fates.items()}
        self.submissions: list[tuple[str, int]] = []

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
        # "killed:<worker>": the task's worker died while running it
        worker = fate.split(":", 1)[1]
        killed = distributed.KilledWorker(key, SimpleNamespace(address=worker), 0)
        return ScriptedFuture(key, "error", exception=killed)

    def nthreads(self) -> dict[str, int]:
        return {"tcp://w1": 1}

    def as_current(self) -> contextlib.AbstractContextManager:
        return contextlib.nullcontext()

    def subscribe_topic(self, *a: Any) -> None:
        pass

    def unsubscribe_topic(self, *a: Any) -> None:
        pass

    def register_plugin(self, *a: Any, **kw: Any) -> None:
        pass

    def close(self, timeout: float = 0) -> None:
        pass


def run(monkeypatch: pytest.MonkeyPatch, fates: dict[str, list[str]]) -> tuple[dict[str, PairOutcome], ScriptedClient]:
    """The outcomes of pairs ``a``, ``b`` (seeds 11, 12) under the scripted ``fates``."""
    client = ScriptedClient(fates)
    monkeypatch.setattr(dask_executor, "_connect", lambda scheduler, n: (client, None))
    monkeypatch.setattr(distributed, "wait", lambda futures, timeout, return_when: (set(futures), set()))
    specs = [PairSpec(pid, Path(f"{pid}_src.ply"), Path(f"{pid}_tgt.ply")) for pid in ("a", "b")]
    config = config_from_dict({}, "<test>")
    outcomes = dask_executor.dask_outcomes([(specs[0], 11), (specs[1], 12)], config, 1, None, 600.0,
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
