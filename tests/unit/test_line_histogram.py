"""The lock-free line histograms export what Prometheus expects: cumulative, ``le`` inclusive."""

from __future__ import annotations

from gateway.metrics import GatewayMetrics


def test_buckets_are_cumulative_and_upper_bounds_inclusive() -> None:
    metrics = GatewayMetrics()
    histogram = metrics.wire_duration.labels("a")
    for value in (0.001, 0.0011, 0.003, 7.0):
        histogram.observe(value)
    sample = metrics.registry.get_sample_value
    name = "modbus_gateway_wire_duration_seconds"
    assert sample(f"{name}_bucket", {"line": "a", "le": "0.001"}) == 1  # 0.001 <= 0.001
    assert sample(f"{name}_bucket", {"line": "a", "le": "0.0025"}) == 2
    assert sample(f"{name}_bucket", {"line": "a", "le": "0.005"}) == 3
    assert sample(f"{name}_bucket", {"line": "a", "le": "5.0"}) == 3
    assert sample(f"{name}_bucket", {"line": "a", "le": "+Inf"}) == 4
    assert sample(f"{name}_count", {"line": "a"}) == 4
    assert sample(f"{name}_sum", {"line": "a"}) == 0.001 + 0.0011 + 0.003 + 7.0


def test_a_line_keeps_its_series_across_lookups() -> None:
    metrics = GatewayMetrics()
    metrics.request_duration_for("a").observe(0.5)
    metrics.request_duration_for("a").observe(0.5)
    count = metrics.registry.get_sample_value(
        "modbus_gateway_request_duration_seconds_count", {"line": "a"}
    )
    assert count == 2
