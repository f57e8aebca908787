"""The soak command: its arithmetic, and a short real run (a smoke test, not a timed assertion;
the 30-minute run is docs/soak.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from clients.cli import main
from clients.soak import metric_values, slope_per_hour


def test_metrics_text_is_read_with_labelled_series_summed():
    text = (
        "# HELP x\n# TYPE x gauge\nprocess_resident_memory_bytes 3.2e+08\n"
        'stylestream_active_sessions{model="lti"} 3.0\nstylestream_active_sessions{model="erd"} 2.0\n'
    )
    values = metric_values(text)
    assert values == {"process_resident_memory_bytes": 3.2e8, "stylestream_active_sessions": 5.0}


def test_slope_leaves_out_the_warm_up_and_is_per_hour():
    t = np.arange(0, 1800, 10.0)
    rss = np.where(t < 300, 300 + t / 10, 330 + 0.001 * (t - 300))  # fast warm-up, then 3.6 MB/h
    assert slope_per_hour(t, rss, warmup_s=300) == pytest.approx(3.6)
    assert np.isnan(slope_per_hour(t[:2], rss[:2], warmup_s=0))


def test_a_short_soak_run_writes_samples_a_plot_and_the_page(tmp_path, mocap_data):
    out, doc = tmp_path / "soak", tmp_path / "soak.md"
    assert (
        main(
            [
                "soak",
                "--minutes",
                "0.1",
                "--sessions",
                "2",
                "--fps",
                "30",
                "--interval",
                "0.5",
                "--session-seconds",
                "4",
                "--out",
                str(out),
                "--doc",
                str(doc),
            ]
        )
        == 0
    )
    report = json.loads(out.with_suffix(".json").read_text())
    samples, summary = report["samples"], report["summary"]
    assert len(samples) >= 5 and all(s["rss_mb"] > 50 for s in samples)  # a real server process, models loaded
    assert 1 <= max(s["sessions"] for s in samples) <= 2 and samples[-1]["frames"] > 0
    assert summary["frames"] > 0 and summary["client_dropped"] >= 0
    assert out.with_suffix(".png").stat().st_size > 10_000
    page = doc.read_text()
    assert "![server RSS and Python heap over the soak](soak.png)" in page and "MB/h" in page
