"""The client's progress bars: the job's, and one per running part of a job run as parts."""

from __future__ import annotations

import io

from service.client import Event, JobBars


def test_a_bar_per_running_part_and_one_for_the_job():
    out = io.StringIO()
    bars = JobBars(out, width=10)
    bars.on_event(Event(1, "state", {"state": "running", "fraction": 0.0, "stage": "parts"}))
    bars.on_event(Event(2, "part", {"part": 0, "event": "state", "state": "running",
                                    "fraction": 0.0, "stage": "starting"}))
    bars.on_event(Event(3, "part", {"part": 1, "event": "progress", "fraction": 0.5,
                                    "stage": "appearance", "frame": 1, "frames": 2,
                                    "iteration": 50, "iterations": 100, "eta_s": 75.0}))
    bars.on_event(Event(3, "progress", {"fraction": 0.25, "stage": "parts", "frames": 6,
                                        "frame": 0, "eta_s": 90.0}))
    text = [line for _, line, _ in bars.lines()]
    assert text[0].startswith("      [##........]  25.0%  parts") and "ETA 1m30s" in text[0]
    assert text[1].startswith("  part   0 [..........]   0.0%  starting")
    assert text[2].startswith("  part   1 [#####.....]  50.0%  appearance")
    assert "frame 1/2 step 50/100  ETA 1m15s" in text[2]
    # A part that ended has no bar any more.
    bars.on_event(Event(4, "part", {"part": 0, "event": "state", "state": "succeeded",
                                    "fraction": 1.0, "stage": "succeeded"}))
    assert [key for key, _, _ in bars.lines()] == ["job", 1]
    bars.close()
    assert "part   1 [#####.....]" in out.getvalue()  # not a terminal: lines as they change
