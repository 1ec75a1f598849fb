"""Prometheus metrics of the daemon (prometheus-client), one registry per daemon.

Job, device and safety gauges are read from the daemon at scrape time; request latency is a histogram
filled by :class:`RequestTimer`, an ASGI middleware (pure ASGI, so streamed responses pass untouched).
Times in seconds, as Prometheus expects.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from prometheus_client import CollectorRegistry, Histogram
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector
from tandemscan.daemon.job_state import JobState

# Buckets (s) of the loop-timing histograms: fine around the 5 ms control-jitter target and the 20 ms period.
TIMING_BUCKETS = (0.0005, 0.001, 0.002, 0.003, 0.004, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.03, 0.05, 0.075, 0.1,
                  0.25, 0.5, 1.0, 2.5)


def timing_histograms(registry: CollectorRegistry) -> tuple[Histogram, Histogram]:
    """(event-loop lag, 50 Hz control-loop lateness) histograms (s): cumulative, so a scraper can take the
    p99 of any interval from two scrapes, where the p99 gauges only cover the recent window."""
    lag = Histogram("tandemscan_event_loop_lag_seconds", "How late the event loop wakes a sleeper",
                    registry=registry, buckets=TIMING_BUCKETS)
    lateness = Histogram("tandemscan_control_lateness_seconds", "How late each safety control tick starts",
                         registry=registry, buckets=TIMING_BUCKETS)
    return lag, lateness

class DaemonCollector(Collector):
    """Gauges computed from ``snapshot()``: ``{"jobs": {state: n}, "devices": [...], "safety": {...},
    "loop_lag_p99_s": float, "control_lateness_p99_s": float}``."""

    def __init__(self, snapshot: Callable[[], dict]):
        self._snapshot = snapshot

    def collect(self):
        s = self._snapshot()
        jobs = GaugeMetricFamily("tandemscan_jobs", "Jobs by state", labels=["state"])
        for state in JobState:
            jobs.add_metric([state], s["jobs"].get(state, 0))
        yield jobs
        dev = GaugeMetricFamily("tandemscan_device_connected", "1 when the device is connected", labels=["device"])
        for d in s["devices"]:
            dev.add_metric([d["name"]], 1.0 if d["connected"] else 0.0)
        yield dev
        rec = GaugeMetricFamily("tandemscan_device_reconnects", "Reconnect attempts since start", labels=["device"])
        for d in s["devices"]:
            rec.add_metric([d["name"]], d["reconnects"])
        yield rec
        yield GaugeMetricFamily("tandemscan_safety_latched", "1 while a safety stop is latched",
                                value=1.0 if s["safety"]["latched"] else 0.0)
        yield GaugeMetricFamily("tandemscan_event_loop_lag_p99_seconds", "Event-loop lag p99 (recent window)",
                                value=s["loop_lag_p99_s"])
        yield GaugeMetricFamily("tandemscan_control_lateness_p99_seconds",
                                "Safety control-loop lateness p99 (recent window)", value=s["control_lateness_p99_s"])


class RequestTimer:
    """ASGI middleware observing the time to the response start per route template and method."""

    def __init__(self, app, registry: CollectorRegistry):
        self.app = app
        self.hist = Histogram("tandemscan_http_request_seconds", "REST latency to the response start",
                              ["method", "route", "status"], registry=registry,
                              buckets=(0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0))

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()

        async def timed_send(message):
            if message["type"] == "http.response.start":
                route = scope.get("route")
                path = getattr(route, "path", "unmatched")
                self.hist.labels(scope["method"], path, str(message["status"])).observe(time.perf_counter() - t0)
            await send(message)

        await self.app(scope, receive, timed_send)
