"""Reading a server's `/metrics` (Prometheus text exposition) with `prometheus_client.parser`, the
parser of the library that writes it, for the load, soak and perf tools and the tests."""

from __future__ import annotations

from collections.abc import Iterator

from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.samples import Sample


def samples(text: str) -> Iterator[Sample]:
    """Every sample (name with its `_bucket`/`_count`/`_total`... suffix, labels, value)."""
    for family in text_string_to_metric_families(text):
        yield from family.samples


def metric_values(text: str) -> dict[str, float]:
    """{sample name: value}, the labelled series of one name summed."""
    out: dict[str, float] = {}
    for s in samples(text):
        out[s.name] = out.get(s.name, 0.0) + s.value
    return out


def histogram_buckets(text: str, name: str, **labels: str) -> dict[float, float]:
    """A histogram's cumulative bucket counts {upper bound (inf for +Inf): count}, for the series
    whose labels include `labels`."""
    out: dict[float, float] = {}
    for s in samples(text):
        if s.name == f"{name}_bucket" and all(s.labels.get(k) == v for k, v in labels.items()):
            bound = float(s.labels["le"])  # "+Inf" parses as inf
            out[bound] = out.get(bound, 0.0) + s.value
    return out
