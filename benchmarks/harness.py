"""Tiny benchmark harness: medians over repeated runs, ratios against a peer.

This machine is shared and noisy: quote medians and ratios measured in the
same run, never a single timing.

Example
-------
>>> from benchmarks.harness import Bench
>>> b = Bench("sum", repeats=5)
>>> b.time("python sum", lambda: sum(range(10_000)))       # doctest: +SKIP
>>> b.time("numpy sum", lambda: np.arange(10_000).sum(), peer="python sum")  # doctest: +SKIP
>>> b.print()                                               # doctest: +SKIP
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from typing import Any, Callable


@dataclass
class Result:
    name: str
    times_s: list[float]
    peer: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def median_s(self) -> float:
        return statistics.median(self.times_s)


@dataclass
class Bench:
    title: str
    repeats: int = 5
    warmup: int = 1
    results: dict[str, Result] = field(default_factory=dict)

    def time(self, name: str, fn: Callable[[], Any], peer: str | None = None, repeats: int | None = None,
             warmup: int | None = None, **extra) -> Result:
        """Run ``fn`` ``warmup`` times untimed, then ``repeats`` times timed."""
        for _ in range(self.warmup if warmup is None else warmup):
            fn()
        times = []
        for _ in range(self.repeats if repeats is None else repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        res = Result(name, times, peer, dict(extra))
        self.results[name] = res
        return res

    def record(self, name: str, times_s: list[float], peer: str | None = None, **extra) -> Result:
        """Record externally measured times (e.g. per-case wall times)."""
        res = Result(name, list(times_s), peer, dict(extra))
        self.results[name] = res
        return res

    def ratio(self, name: str, peer: str) -> float:
        """How many times faster ``name`` is than ``peer`` (median over median)."""
        return self.results[peer].median_s / self.results[name].median_s

    def print(self) -> None:
        print(f"\n== {self.title} ==")
        print(f"{'case':44s} {'median':>11s} {'min':>11s} {'n':>4s}  vs peer")
        for r in self.results.values():
            vs = ""
            if r.peer and r.peer in self.results:
                vs = f"{self.ratio(r.name, r.peer):6.2f}x faster than {r.peer}"
            extra = "  " + ", ".join(f"{k}={v}" for k, v in r.extra.items()) if r.extra else ""
            print(f"{r.name:44s} {_fmt(r.median_s):>11s} {_fmt(min(r.times_s)):>11s} {len(r.times_s):4d}  {vs}{extra}")


def _fmt(t: float) -> str:
    if t < 1e-3:
        return f"{t * 1e6:.1f} us"
    if t < 1:
        return f"{t * 1e3:.2f} ms"
    return f"{t:.3f} s"
