"""wavelight_cli.console: progress people expect on long work (elapsed, rate with its unit, time
left), plain greppable lines when stderr is not a terminal, one updating tqdm line when it is."""

from __future__ import annotations

import io
import re

from wavelight_cli import console as cm


class _Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_plain_lines_say_elapsed_rate_unit_and_time_left(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(cm.time, "monotonic", clock)
    err = io.StringIO()
    c = cm.Console(stream=err, out=io.StringIO())
    task = c.task("visibility/photo/R32", "casting", 10, "refinement steps")
    for done in range(1, 11):
        clock.now += 2.0  # 2 s per step: 0.5 steps/s
        task.update(done)
    task.close()
    lines = err.getvalue().splitlines()
    assert len(lines) == 10  # one a second at most: each step took 2 s
    assert lines[3] == "visibility/photo/R32: casting [4/10] 40 %, 8.0 s, 0.5 refinement steps/s, about 12.0 s left"
    assert lines[-1] == "visibility/photo/R32: casting [10/10] 100 %, 20.0 s, 0.5 refinement steps/s"  # no ETA at the end


def test_plain_lines_are_at_most_one_a_second_and_the_last_always_shows(monkeypatch):
    clock = _Clock()
    monkeypatch.setattr(cm.time, "monotonic", clock)
    err = io.StringIO()
    task = cm.Console(stream=err, out=io.StringIO()).task("insert", "rendering", 1000, "pixels")
    for done in range(1, 1001):
        clock.now += 0.01  # 10 s in all
        task.update(done)
    lines = err.getvalue().splitlines()
    assert 9 <= len(lines) <= 11
    assert lines[-1].startswith("insert: rendering [1000/1000] 100 %, 10.0 s, 100 pixels/s")
    long_eta = [ln for ln in lines if "left" in ln]
    assert long_eta and all(re.search(r"about \d+\.\d s left", ln) for ln in long_eta)


def test_rates_and_durations_read_as_people_write_them():
    assert cm._rate(6.1e6) == "6.1 M" and cm._rate(52_000) == "52 k" and cm._rate(0.891) == "0.891"
    assert cm._duration(4.04) == "4.0 s" and cm._duration(125) == "2 min 05 s"


def test_quiet_prints_no_progress_but_results(monkeypatch):
    err, out = io.StringIO(), io.StringIO()
    c = cm.Console(quiet=True, stream=err, out=out)
    task = c.task("solve", "rounds", 3)
    for d in (1, 2, 3):
        task.update(d)
    c.say("a note")
    c.result("solve: the result")
    assert err.getvalue() == "" and out.getvalue() == "solve: the result\n"


def test_a_terminal_gets_one_updating_line():
    err = _Tty()
    c = cm.Console(stream=err, out=io.StringIO())
    assert c.interactive
    task = c.task("visibility", "casting", 5, "steps")
    for d in range(1, 6):
        task.update(d, extra="3 of 100 wrong")
    c.say("visibility: done")  # a note clears the bar first, then prints on its own line
    task.close()
    text = err.getvalue()
    assert "\r" in text  # tqdm redraws the same line
    assert "\n".join(text.replace("\r", "\n").split("\n")).count("visibility: done") == 1
    assert "visibility: casting" in text and " steps" in text
    assert not re.search(r"^visibility: casting \[\d/5\]", text, re.M)  # not the plain lines
