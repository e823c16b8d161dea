"""The client's progress bars (tqdm): the job's, and one per running part of a job run as parts;
lines as they change where the stream is not a terminal, bars redrawn in place where it is."""

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
    assert text[0].startswith("      [##........]  25.0%  parts") and "ETA 01:30" in text[0]
    assert text[1].startswith("  part   0 [..........]   0.0%  starting")
    assert text[2].startswith("  part   1 [#####.....]  50.0%  appearance")
    assert "frame 1/2 step 50/100  ETA 01:15" in text[2]
    # A part that ended has no bar any more.
    bars.on_event(Event(4, "part", {"part": 0, "event": "state", "state": "succeeded",
                                    "fraction": 1.0, "stage": "succeeded"}))
    assert [key for key, _, _ in bars.lines()] == ["job", 1]
    bars.close()
    assert "part   1 [#####.....]" in out.getvalue()  # not a terminal: lines as they change


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_on_a_terminal_each_bar_is_redrawn_in_place_and_an_ended_part_is_cleared():
    out = Terminal()
    bars = JobBars(out, width=10)
    bars.on_event(Event(1, "state", {"state": "running", "fraction": 0.0, "stage": "parts"}))
    bars.on_event(Event(2, "part", {"part": 0, "event": "progress", "fraction": 0.2,
                                    "stage": "appearance", "eta_s": 3725.0}))
    bars.on_event(Event(3, "part", {"part": 1, "event": "progress", "fraction": 0.5,
                                    "stage": "geometry"}))
    assert {"job", 0, 1} == set(key for key, _, _ in bars.lines())
    bars.on_event(Event(4, "part", {"part": 0, "event": "state", "state": "succeeded",
                                    "fraction": 1.0, "stage": "succeeded"}))
    bars.on_event(Event(5, "part", {"part": 2, "event": "progress", "fraction": 0.1,
                                    "stage": "appearance"}))
    bars.on_event(Event(6, "progress", {"fraction": 0.75, "stage": "parts"}))
    text = out.getvalue()
    assert "\r  part   0 [##........]  20.0%  appearance   ETA 1:02:05" in text
    assert "\r  part   1 [#####.....]  50.0%  geometry" in text
    assert "\r  part   2 [#.........]  10.0%  appearance" in text
    assert "\x1b[A" in text  # drawn below the job's line, the cursor moved back up
    # Part 0's bar was cleared when it ended (its line blanked before part 2's bar came).
    cleared = text.index("\r" + " " * 20)
    assert text.index("part   0 [##") < cleared < text.index("part   2 [#.")
    assert "\r      [#######...]  75.0%  parts" in text
    bars.close()
    assert out.getvalue().endswith("75.0%  parts      \n")  # the job's bar stays
