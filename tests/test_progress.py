"""fusion_depth.utils.progress: periodic log lines off a terminal, a bar on one (a fake clock)."""

from __future__ import annotations

import io
import logging

import pytest

from fusion_depth.utils.progress import Progress, format_duration, track

LOGGER = "fusion_depth.test_progress"


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == LOGGER]


def test_lines_come_at_most_every_every_s_with_counts_rate_and_eta(caplog) -> None:
    clock = Clock()
    logger = logging.getLogger(LOGGER)
    with caplog.at_level(logging.INFO, logger=LOGGER):
        with Progress(
            500, "predict", unit="images", every_s=60, terminal=False, logger=logger, clock=clock
        ) as progress:
            clock.now += 30
            progress.advance(60)  # 30 s in: too early for a line
            assert _lines(caplog) == []
            clock.now += 27
            progress.advance(60)  # 57 s: still too early
            assert _lines(caplog) == []
            clock.now += 3
            progress.advance(6)  # 60 s, 126 done: 2.1/s, 374 left -> 178 s
            assert _lines(caplog) == ["predict: 126/500 images, 2.1/s, ETA 3 min"]
            clock.now += 59
            progress.advance(100)  # 59 s after the last line: none
            assert len(_lines(caplog)) == 1
            clock.now += 1
            progress.advance(14)  # 120 s, 240 done: 2/s, 260 left -> 130 s
            assert _lines(caplog)[1] == "predict: 240/500 images, 2/s, ETA 2 min"
            clock.now += 130
            progress.advance(260)
        assert progress.done == 500
    # Once more at the end, with the time taken instead of an ETA.
    assert _lines(caplog) == [
        "predict: 126/500 images, 2.1/s, ETA 3 min",
        "predict: 240/500 images, 2/s, ETA 2 min",
        "predict: 500/500 images in 4 min, 2/s",
    ]


def test_a_short_loop_logs_only_the_final_line(caplog) -> None:
    clock = Clock()
    logger = logging.getLogger(LOGGER)
    with caplog.at_level(logging.INFO, logger=LOGGER):
        for _ in track(
            range(3),
            "prepare topview val",
            unit="frames",
            terminal=False,
            logger=logger,
            clock=clock,
        ):
            clock.now += 2
    assert _lines(caplog) == ["prepare topview val: 3/3 frames in 6 s, 0.5/s"]


def test_track_counts_items_once_their_body_is_done_and_an_error_still_logs(caplog) -> None:
    clock = Clock()
    logger = logging.getLogger(LOGGER)
    seen = []
    with caplog.at_level(logging.INFO, logger=LOGGER), pytest.raises(KeyError):
        for item in track(
            iter("abcdef"), "scan", every_s=5, terminal=False, logger=logger, clock=clock
        ):
            seen.append(item)
            clock.now += 2
            if item == "d":
                raise KeyError(item)  # d's body never finished: 3 done
    assert seen == list("abcd")
    # Unknown total (an iterator): a count without "/total" and no ETA. A line at 6 s (3 done),
    # then the final one when the loop was left at 8 s.
    assert _lines(caplog) == ["scan: 3 items, 0.5/s", "scan: 3 items in 8 s, 0.38/s"]


def test_nothing_is_logged_on_a_terminal_and_the_bar_is_drawn(caplog) -> None:
    clock = Clock()
    logger = logging.getLogger(LOGGER)
    stream = io.StringIO()
    with caplog.at_level(logging.DEBUG, logger=LOGGER):
        with Progress(
            4, "predict", every_s=1, terminal=True, logger=logger, stream=stream, clock=clock
        ) as progress:
            for _ in range(4):
                clock.now += 10
                progress.advance()
    assert _lines(caplog) == []
    assert progress.done == 4
    assert "predict" in stream.getvalue() and "4/4" in stream.getvalue()


def test_terminal_defaults_to_whether_the_stream_is_one(caplog) -> None:
    class Tty(io.StringIO):
        def isatty(self) -> bool:
            return True

    assert Progress(1, "x", stream=Tty()).terminal is True
    assert Progress(1, "x", stream=io.StringIO()).terminal is False


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"total": -1}, "total=-1"),
        ({"total": 2.5}, "total=2.5"),
        ({"total": 3, "every_s": 0}, "every_s=0"),
    ],
)
def test_bad_arguments_are_named(kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        Progress(description="x", **kwargs)


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (0.4, "0 s"),
        (42, "42 s"),
        (89, "89 s"),
        (178, "3 min"),
        (5399, "90 min"),
        (7500, "2 h 5 min"),
    ],
)
def test_durations_are_short(seconds, text) -> None:
    assert format_duration(seconds) == text
