"""Preparing a split with several workers, in shards, and from several processes at once: each
frame is made once, the cache is the same file for file as a serial prepare's, and kills, broken
frames and a full disk leave it whole and resumable."""

from __future__ import annotations

import errno
import json
import multiprocessing
import os
import random
import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import file_bytes

from fusion_depth.config.arguments import config_message
from fusion_depth.data import cache as cache_module
from fusion_depth.data.cache import (
    CLAIMS_DIR,
    CacheFullError,
    IncompleteSplitError,
    PreparedFrame,
    PrepareOptions,
    SkippedFramesError,
    SplitJob,
    prepare_options,
    prepare_split,
    prepare_splits,
)
from fusion_depth.errors import ArgumentError
from fusion_depth.utils.atomic import write_atomic

FRAMES = [f"scene/{k:03d}" for k in range(12)]
PARAMS = {"dataset": "toy", "size": [8, 12]}


def make_frame(frame_id: str, calls: Path | None = None, delay: float = 0.0) -> PreparedFrame:
    """A frame that is a pure function of its id; each call appends the id to ``calls``."""
    if calls is not None:
        with calls.open("a") as f:
            f.write(frame_id + "\n")
    time.sleep(delay)
    k = int(frame_id.split("/")[1])
    rng = np.random.default_rng(k)
    image = rng.integers(0, 256, (8, 12, 3), dtype=np.uint8)
    depth = np.where(rng.random((8, 12)) < 0.3, rng.uniform(1, 80, (8, 12)), 0.0)
    return PreparedFrame(image, depth * (rng.random((8, 12)) < 0.5), depth, "day", filled=depth)


def prepare(cache: Path, options: PrepareOptions | None = None, make=make_frame, **kwargs) -> Path:
    with prepare_options(options or PrepareOptions()):
        return prepare_split(cache, "train", FRAMES, make, PARAMS, **kwargs)


@pytest.fixture
def serial(tmp_path: Path) -> dict[str, bytes]:
    """The cache one serial, uninterrupted prepare writes."""
    prepare(tmp_path / "serial")
    return file_bytes(tmp_path / "serial")


def test_workers_write_the_same_cache_as_one_process(tmp_path, serial) -> None:
    calls = tmp_path / "calls.txt"
    prepare(tmp_path / "parallel", PrepareOptions(workers=3), make=lambda f: make_frame(f, calls))
    assert file_bytes(tmp_path / "parallel") == serial
    assert sorted(calls.read_text().split()) == sorted(FRAMES), "a frame was made twice"


def test_each_worker_runs_its_blas_on_its_share_of_the_cores(tmp_path, monkeypatch) -> None:
    """Two workers on 2 cores run one BLAS thread each (SuperLU's dense kernels), not the
    thread per core each would start: four threads on two cores wait on one another."""
    from threadpoolctl import threadpool_info, threadpool_limits

    threads_seen = tmp_path / "threads.txt"

    def make_and_count(frame_id: str) -> PreparedFrame:
        with threads_seen.open("a") as f:
            f.write(f"{max(pool['num_threads'] for pool in threadpool_info())}\n")
        return make_frame(frame_id)

    monkeypatch.setattr(cache_module, "usable_cores", lambda: 2)
    with threadpool_limits(limits=2):  # the BLAS default on 2 cores: a thread per core
        prepare(tmp_path / "cache", PrepareOptions(workers=2), make=make_and_count)
    assert threads_seen.read_text().split() == ["1"] * len(FRAMES)


@pytest.mark.slow
def test_a_fresh_process_limits_the_blas_its_fills_load_after_the_fork(tmp_path) -> None:
    """In a fresh ``prepare`` SciPy, and the OpenBLAS it links, is first loaded by a fill, in
    the worker. threadpoolctl's limit covers only the libraries loaded when it is set, so the
    worker also sets the thread count such a library reads when it starts: two workers on 2
    cores run one BLAS thread each through every fill, not two each (which made a light fill
    2-15x slower, docs/results/prepare.md)."""
    script = textwrap.dedent(
        f"""
        import sys
        from pathlib import Path
        import numpy as np
        from threadpoolctl import threadpool_info
        from fusion_depth.data import cache
        from fusion_depth.data.filling import fill_depth
        assert "scipy.spatial" not in sys.modules, "a fresh process: SciPy not loaded yet"
        cache.usable_cores = lambda: 2
        seen = open({str(tmp_path / "threads.txt")!r}, "a")

        def make(frame_id):
            rng = np.random.default_rng(int(frame_id))
            depth = np.where(rng.random((24, 40)) < 0.2, rng.uniform(1, 80, (24, 40)), 0.0)
            image = rng.integers(0, 256, (24, 40, 3), dtype=np.uint8)
            filled = fill_depth(depth, image, "colorization")
            fill_depth(depth, image, "linear")
            blas = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
            seen.write(f"{{len(blas)}} {{max(blas)}}\\n")
            seen.flush()
            return cache.PreparedFrame(image, depth, depth, "day", filled=filled)

        with cache.prepare_options(cache.PrepareOptions(workers=2)):
            cache.prepare_split(
                Path({str(tmp_path / "cache")!r}), "train", [f"{{k}}" for k in range(6)], make,
                {{"dataset": "toy"}},
            )
        """
    )
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "2"}  # a thread per core, on any machine
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    rows = [line.split() for line in (tmp_path / "threads.txt").read_text().splitlines()]
    assert len(rows) == 6
    # NumPy's and SciPy's OpenBLAS are both loaded by then, and both run one thread.
    assert all(int(count) >= 2 and int(most) == 1 for count, most in rows), rows


def test_a_linear_fill_runs_one_blas_thread(monkeypatch) -> None:
    """The triangulation's LAPACK calls are 2x2 solves: a second BLAS thread only slows them,
    so a linear fill runs one whatever the process allows."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from fusion_depth.data import filling

    seen = []
    fill_linear = filling._fill_linear

    def counting(*args, **kwargs):
        seen.append(max(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"))
        return fill_linear(*args, **kwargs)

    monkeypatch.setattr(filling, "_fill_linear", counting)
    rng = np.random.default_rng(0)
    depth = np.where(rng.random((16, 20)) < 0.3, rng.uniform(1, 80, (16, 20)), 0.0)
    image = rng.integers(0, 256, (16, 20, 3), dtype=np.uint8)
    with threadpool_limits(limits=2, user_api="blas"):
        for method in ("linear", "linear_hull"):
            filling.fill_depth(depth, image, method)
        after = max(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")
    assert seen == [1, 1] and after == 2  # the process's own setting is back afterwards


@pytest.mark.parametrize("workers", [1, 3])
def test_progress_counts_each_frame_once_whatever_the_workers(tmp_path, caplog, workers) -> None:
    """Off a terminal the last progress line says 12/12, not a count per worker (each worker
    walks the whole list and skips the frames others claimed)."""
    caplog.set_level("INFO", logger=cache_module.__name__)
    prepare(tmp_path / "cache", PrepareOptions(workers=workers))
    lines = [
        r.getMessage() for r in caplog.records if re.search(r"\d+/\d+ frames in", r.getMessage())
    ]
    assert lines and f": {len(FRAMES)}/{len(FRAMES)} frames in" in lines[-1], lines


def test_shards_share_the_split_and_the_last_writes_the_index(tmp_path, serial) -> None:
    cache = tmp_path / "sharded"
    for shard in (0, 1):
        with pytest.raises(IncompleteSplitError) as info:
            prepare(cache, PrepareOptions(shard=shard, num_shards=3, finish_sharded=True))
    assert (info.value.done, info.value.total) == (8, 12)
    assert len(list((cache / "train").glob("0*.json"))) == 8
    # Training on the split does not prepare the other shard's frames: it names what is missing.
    with pytest.raises(IncompleteSplitError, match=r"8 of 12 frames prepared, 4 missing.*3 shards"):
        prepare(cache)
    prepare(cache, PrepareOptions(shard=2, num_shards=3, finish_sharded=True))
    assert file_bytes(cache) == serial
    prepare(cache)  # usable now


def test_a_shard_joined_with_another_num_shards_is_told_both(tmp_path, serial, caplog) -> None:
    """Shards of different counts split the frames differently, so some frames fall to no shard
    and every shard waits. A shard that joins (or resumes) a split started with another
    ``num_shards`` says so in one line naming both counts, when it starts and in its hint; so
    does a shard of the first count that runs after it. Shards of one count are told nothing."""
    cache = tmp_path / "mixed"
    with pytest.raises(IncompleteSplitError) as info:
        prepare(cache, PrepareOptions(shard=0, num_shards=3, finish_sharded=True))
    assert info.value.hint is None
    for shard, num_shards, other in ((1, 2, 3), (0, 3, 2)):
        caplog.clear()
        with caplog.at_level("WARNING", logger=cache_module.__name__):
            with pytest.raises(IncompleteSplitError) as info:
                options = PrepareOptions(shard=shard, num_shards=num_shards, finish_sharded=True)
                prepare(cache, options)
        hint = info.value.hint
        assert hint is not None and "\n" not in hint
        assert f"num_shards={other}" in hint and f"num_shards={num_shards}" in hint
        assert hint in str(info.value)
        if num_shards == 2:  # it joined shards of 3: said when it starts
            warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
            assert any("num_shards=3" in w and "num_shards=2" in w for w in warned), warned
    prepare(cache, PrepareOptions(finish_sharded=True))  # a plain prepare finishes it
    assert file_bytes(cache) == serial


def test_a_plain_prepare_finishes_what_shards_left(tmp_path, serial) -> None:
    cache = tmp_path / "finish"
    with pytest.raises(IncompleteSplitError):
        prepare(cache, PrepareOptions(shard=1, num_shards=4, finish_sharded=True))
    prepare(cache, PrepareOptions(workers=2, finish_sharded=True))
    assert file_bytes(cache) == serial


def test_leftovers_of_a_killed_prepare_are_removed(tmp_path, serial) -> None:
    cache = tmp_path / "killed"
    with pytest.raises(IncompleteSplitError):
        prepare(cache, PrepareOptions(shard=0, num_shards=2, finish_sharded=True))
    split = cache / "train"
    # What a kill during frame 3's write leaves: a temporary array and the dead process's claim.
    (split / ".000003.image.npy.x1y2z3.npy").write_bytes(b"\x93NUMPY half")
    (split / ".000003.json.abcdef.tmp").write_text("{")
    dead = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True
    )
    (split / CLAIMS_DIR).mkdir(exist_ok=True)
    claim = {"host": os.uname().nodename, "pid": int(dead.stdout)}
    (split / CLAIMS_DIR / "000003").write_text(json.dumps(claim))
    prepare(cache, PrepareOptions(workers=2, finish_sharded=True))
    assert file_bytes(cache) == serial


def _prepare_in_a_process(cache: Path, calls: Path) -> None:
    prepare(cache, make=lambda f: make_frame(f, calls, delay=0.05))


def test_two_processes_on_one_cache_make_each_frame_once(tmp_path, serial) -> None:
    cache, calls = tmp_path / "shared", tmp_path / "calls.txt"
    context = multiprocessing.get_context("fork")
    processes = [context.Process(target=_prepare_in_a_process, args=(cache, calls)) for _ in "ab"]
    for process in processes:
        process.start()
    for process in processes:
        process.join(60)
        assert process.exitcode == 0
    assert sorted(calls.read_text().split()) == sorted(FRAMES), "a frame was made twice"
    assert file_bytes(cache) == serial


def test_a_broken_frame_is_skipped_by_its_worker_and_the_others_go_on(tmp_path) -> None:
    def broken(frame_id: str) -> PreparedFrame:
        if frame_id in ("scene/004", "scene/009"):
            raise ValueError(f"{frame_id}.png: truncated")
        return make_frame(frame_id)

    cache = tmp_path / "broken"
    with pytest.raises(SkippedFramesError) as info:
        prepare(cache, PrepareOptions(workers=3), make=broken, on_error="skip")
    (report,) = info.value.reports
    assert [s.frame_id for s in report.skipped] == ["scene/004", "scene/009"]
    assert len(list((cache / "train").glob("0*.json"))) == 10
    assert not (cache / "train" / "index.json").exists()
    assert not list((cache / "train").glob(".0*"))  # no temporary file left


def two_splits(cache: Path, make=make_frame) -> list[SplitJob]:
    """A train split of every frame and a val split of the first four."""
    return [
        SplitJob(cache, "train", FRAMES, make, PARAMS),
        SplitJob(cache, "val", FRAMES[:4], make, PARAMS),
    ]


def test_one_set_of_workers_serves_every_split(tmp_path) -> None:
    """The workers are forked once for all the splits (a worker with no frame of one split
    left goes on to the next instead of waiting for the others), and each split's files are
    the serial prepare's."""
    makers = tmp_path / "makers.txt"

    def noting_its_process(frame_id: str) -> PreparedFrame:
        with makers.open("a") as f:
            f.write(f"{os.getpid()}\n")
        return make_frame(frame_id, delay=0.02)

    with prepare_options(PrepareOptions()):
        prepare_splits(two_splits(tmp_path / "serial"))
    with prepare_options(PrepareOptions(workers=2)):
        prepare_splits(two_splits(tmp_path / "workers", noting_its_process))
    processes = set(makers.read_text().split())
    assert len(processes) <= 2 and str(os.getpid()) not in processes, processes
    assert len(makers.read_text().split()) == len(FRAMES) + 4  # each frame made once
    assert file_bytes(tmp_path / "workers") == file_bytes(tmp_path / "serial")


def test_skipped_frames_are_reported_by_split_when_workers_share_the_splits(tmp_path) -> None:
    def broken(frame_id: str) -> PreparedFrame:
        if frame_id == "scene/002":  # in both splits: each reports it, neither gets an index
            raise ValueError(f"{frame_id}.png: truncated")
        if frame_id == "scene/007":  # in train only
            raise ValueError(f"{frame_id}.png: truncated")
        return make_frame(frame_id)

    cache = tmp_path / "broken"
    with prepare_options(PrepareOptions(workers=2)):
        with pytest.raises(SkippedFramesError) as info:
            prepare_splits(two_splits(cache, broken), on_error="skip")
    train, val = info.value.reports
    assert (train.split, [s.frame_id for s in train.skipped]) == (
        "train",
        ["scene/002", "scene/007"],
    )
    assert (val.split, [s.frame_id for s in val.skipped]) == ("val", ["scene/002"])
    assert not (cache / "train" / "index.json").exists()
    assert not (cache / "val" / "index.json").exists()
    assert len(list((cache / "val").glob("0*.json"))) == 3


def test_an_error_in_one_worker_stops_them_all_and_leaves_no_half_file(tmp_path) -> None:
    def failing(frame_id: str) -> PreparedFrame:
        if frame_id == "scene/005":
            raise ValueError("bad frame")
        return make_frame(frame_id, delay=0.05)

    cache = tmp_path / "raise"
    with pytest.raises(ValueError, match="bad frame"):
        prepare(cache, PrepareOptions(workers=3), make=failing)
    assert not list((cache / "train").glob(".0*"))
    assert len(list((cache / "train").glob("0*.json"))) < len(FRAMES)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_a_shard_killed_at_a_random_moment_and_run_again_gives_the_serial_cache(
    tmp_path, serial, seed
) -> None:
    """Shard 0 of 2 (two workers) is killed with SIGKILL, parent and workers at once, at a
    random moment after its first frame; shard 1 runs, shard 0 runs again: the serial cache,
    file for file (a dead process's claims and temporary files taken over or removed)."""
    cache = tmp_path / "sharded"
    shard = "PrepareOptions(shard=0, num_shards=2, workers=2, finish_sharded=True)"
    script = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_prepare_parallel import PrepareOptions, make_frame, prepare
        from pathlib import Path
        prepare(Path({str(cache)!r}), {shard}, make=lambda f: make_frame(f, delay=0.4))
        """
    )
    process = subprocess.Popen([sys.executable, "-c", script], start_new_session=True)
    deadline = time.monotonic() + 60
    while not list((cache / "train").glob("0*.json")) and time.monotonic() < deadline:
        time.sleep(0.01)
    # The shard's 6 frames take 1.2 s on its two workers, 0.8 s of it after the first.
    time.sleep(random.Random(seed).uniform(0.0, 0.7))
    os.killpg(process.pid, signal.SIGKILL)
    process.wait(timeout=60)
    try:
        prepare(cache, PrepareOptions(shard=1, num_shards=2, finish_sharded=True))
    except IncompleteSplitError:
        pass  # shard 0 was killed before its last frame
    prepare(cache, PrepareOptions(shard=0, num_shards=2, workers=2, finish_sharded=True))
    assert file_bytes(cache) == serial


def test_ctrl_c_stops_every_worker_and_leaves_no_temporary_file(tmp_path, serial) -> None:
    cache = tmp_path / "interrupted"
    script = textwrap.dedent(
        f"""
        import signal, sys
        # As from a terminal: a test runner's worker may ignore SIGINT, and children inherit it.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_prepare_parallel import PrepareOptions, make_frame, prepare
        from pathlib import Path
        prepare(Path({str(cache)!r}), PrepareOptions(workers=2),
                make=lambda f: make_frame(f, delay=2.0))
        """
    )
    process = subprocess.Popen(
        [sys.executable, "-c", script], start_new_session=True, stderr=subprocess.PIPE
    )
    # 2 s a frame: the split takes 12 s, so Ctrl-C lands mid-split even on a loaded machine.
    deadline = time.monotonic() + 60
    while not list((cache / "train").glob("0*.json")) and time.monotonic() < deadline:
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGINT)  # what Ctrl-C sends: the whole process group
    _, stderr = process.communicate(timeout=60)
    done = len(list((cache / "train").glob("0*.json")))
    why = f"exit {process.returncode}, {done} frames done, stderr: {stderr.decode()[-2000:]}"
    assert process.returncode != 0 and b"KeyboardInterrupt" in stderr, why
    assert 0 < done < len(FRAMES), why
    assert not list((cache / "train").glob(".0*")), "a temporary file was left"
    prepare(cache)
    assert file_bytes(cache) == serial


def test_a_worker_killed_mid_write_leaves_no_temporary_file_but_anothers_stays(
    tmp_path, serial, monkeypatch
) -> None:
    """A worker dies (SIGKILL) between creating frame 3's temporary array and renaming it:
    prepare stops with one line and removes that file, but not the temporary file of a frame
    another live process claims; once that process is gone, the next run gives the serial
    cache."""
    cache, split = tmp_path / "worker-killed", tmp_path / "worker-killed" / "train"
    real_write, parent = cache_module.write_npy, os.getpid()

    def half_then_killed(tmp: Path) -> None:
        tmp.write_bytes(b"\x93NUMPY half")
        os.kill(os.getpid(), signal.SIGKILL)

    def killed_mid_write(path, array) -> None:
        if os.getpid() != parent and Path(path).name.startswith("000003."):
            write_atomic(path, half_then_killed, suffix=".npy")
        real_write(path, array)

    monkeypatch.setattr(cache_module, "write_npy", killed_mid_write)
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    try:
        split.mkdir(parents=True)
        (split / CLAIMS_DIR).mkdir()
        claim = {"host": os.uname().nodename, "pid": other.pid}
        (split / CLAIMS_DIR / "000011").write_text(json.dumps(claim))
        theirs = split / ".000011.image.npy.x1y2z3.npy"
        theirs.write_bytes(b"\x93NUMPY being written")
        with pytest.raises(ChildProcessError, match=r"a prepare worker died \(killed by SIGKILL"):
            prepare(cache, PrepareOptions(workers=2))
        assert [p.name for p in split.glob(".0*")] == [theirs.name]
    finally:
        other.kill()
        other.wait()
    monkeypatch.setattr(cache_module, "write_npy", real_write)
    prepare(cache, PrepareOptions(workers=2))
    assert file_bytes(cache) == serial


def test_an_interrupt_before_a_writes_guard_leaves_no_temporary_file_in_one_process(
    tmp_path, monkeypatch
) -> None:
    """Ctrl-C lands after frame 3's temporary file is created but before the write's own
    cleanup is armed: prepare in one process still leaves no temporary file."""
    cache, real_write = tmp_path / "one-process", cache_module.write_npy

    def interrupted_after_creating(path, array) -> None:
        path = Path(path)
        if path.name.startswith("000003."):
            (path.parent / f".{path.name}.x1y2z3.npy").write_bytes(b"")
            raise KeyboardInterrupt
        real_write(path, array)

    monkeypatch.setattr(cache_module, "write_npy", interrupted_after_creating)
    with pytest.raises(KeyboardInterrupt):
        prepare(cache, PrepareOptions(workers=1))
    assert not list((cache / "train").glob(".0*"))


@pytest.mark.parametrize(
    "error",
    [
        OSError(errno.ENOSPC, "No space left on device"),
        OSError("479232 requested and 133056 written"),  # numpy's np.save, no errno
    ],
)
def test_a_full_disk_is_one_line_naming_the_cache_and_resumes(
    tmp_path, serial, monkeypatch, error
) -> None:
    cache = tmp_path / "full"
    real_write = cache_module.write_npy
    written = []

    def filling_up(path, array) -> None:
        if len(written) == 7:
            raise error
        written.append(path)
        real_write(path, array)

    monkeypatch.setattr(cache_module, "write_npy", filling_up)
    monkeypatch.setattr(
        cache_module.shutil, "disk_usage", lambda path: type("usage", (), {"free": 4096})()
    )
    with pytest.raises(CacheFullError) as info:
        prepare(cache)
    message = str(info.value)
    assert str(cache) in message and "disk is full" in message and "\n" not in message
    monkeypatch.setattr(cache_module, "write_npy", real_write)
    prepare(cache)
    assert file_bytes(cache) == serial


def test_an_unrelated_write_error_is_not_called_a_full_disk(tmp_path, monkeypatch) -> None:
    def denied(path, array) -> None:
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(cache_module, "write_npy", denied)
    with pytest.raises(PermissionError):
        prepare(tmp_path / "denied")


@pytest.mark.parametrize(
    "options,message",
    [
        ({"workers": 0}, r"prepare.workers=0: expected an integer >= 1"),
        ({"num_shards": 0}, r"prepare.num_shards=0"),
        ({"shard": 3, "num_shards": 3}, r"prepare.shard=3: expected an integer in \[0, 3\)"),
        ({"shard": -1, "num_shards": 2}, r"prepare.shard=-1"),
        ({"workers": True}, r"prepare.workers=True"),
    ],
)
def test_bad_options_are_refused_naming_the_key(options, message) -> None:
    with pytest.raises(ArgumentError) as err:  # naming the argument; a command, the key
        PrepareOptions(**options)
    assert re.match(message, config_message(err.value))
    assert re.match(message.removeprefix("prepare."), str(err.value))


# --- processes: workers die with their parent, takeovers are atomic, Ctrl-C is quick ------------


def _children(pid: int) -> list[int]:
    """The pids of ``pid``'s child processes (Linux's /proc)."""
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return [int(p) for p in path.read_text().split()] if path.exists() else []


def _running(pid: int) -> bool:
    """Whether ``pid`` is a process that still runs (a zombie waiting to be reaped does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


# Work a frame does in C, where no Python signal handler runs until it returns (as SuperLU's
# solve in the filling): about 5 s on a 2024 CPU.
BUSY = "sum(range(400_000_000))"


def test_a_parents_sigkill_leaves_no_worker_running(tmp_path) -> None:
    cache = tmp_path / "orphans"
    script = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        from test_prepare_parallel import PrepareOptions, make_frame, prepare
        from pathlib import Path
        prepare(Path({str(cache)!r}), PrepareOptions(workers=2),
                make=lambda f: ({BUSY}, make_frame(f))[1])
        """
    )
    process = subprocess.Popen([sys.executable, "-c", script], start_new_session=True)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 60
        while len(_children(process.pid)) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        workers = _children(process.pid)
        assert len(workers) == 2
        time.sleep(0.5)  # both are inside a frame's C work now
        process.kill()  # the parent alone, as kill -9 <pid>
        process.wait(timeout=10)
        time.sleep(2.0)
        assert [pid for pid in workers if _running(pid)] == []
    finally:
        for pid in [process.pid, *workers]:
            if _running(pid):
                os.kill(pid, signal.SIGKILL)
        process.wait(timeout=10)


def _take_over_in_rounds(split: Path, rounds: int, start: Any, done: Any, wins: Any) -> None:
    for _ in range(rounds):
        start.wait()
        wins.put(cache_module._claim(split, "000000"))
        done.wait()


def test_two_takeovers_of_one_dead_claim_never_both_succeed(tmp_path) -> None:
    """Two processes find the same dead claim at once, 2000 times: each time exactly one of
    them holds it afterwards (without the lock both did, about half the time)."""
    split, rounds = tmp_path / "train", 2000
    (split / CLAIMS_DIR).mkdir(parents=True)
    script = "import os; print(os.getpid())"
    dead = subprocess.run([sys.executable, "-c", script], capture_output=True)
    stale = json.dumps({"host": os.uname().nodename, "pid": int(dead.stdout)})
    context = multiprocessing.get_context("fork")
    start, done, wins = context.Barrier(3), context.Barrier(3), context.SimpleQueue()
    racers = [
        context.Process(target=_take_over_in_rounds, args=(split, rounds, start, done, wins))
        for _ in range(2)
    ]
    for racer in racers:
        racer.start()
    both = 0
    try:
        for _ in range(rounds):
            (split / CLAIMS_DIR / "000000").write_text(stale)
            start.wait(timeout=30)
            results = [wins.get(), wins.get()]
            both += results == [True, True]
            assert results.count(True) >= 1, "nobody took over a dead claim"
            (split / CLAIMS_DIR / "000000").unlink()
            done.wait(timeout=30)
    finally:
        for racer in racers:
            racer.join(30)
    assert both == 0, f"both processes held the claim in {both} of {rounds} rounds"


def _start_prepare_command(tmp_path: Path) -> tuple[subprocess.Popen, Path, list[str], dict]:
    """``python -m fusion_depth.prepare`` on a Top-View folder with two workers, each frame
    spending :data:`BUSY` in C first; returns once the first frame is done."""
    from helpers.topview import write_folder

    root, cache = write_folder(tmp_path / "topview"), tmp_path / "cache"
    argv = [
        "fusion_depth.prepare",
        "dataset=topview",
        f"dataset.root={root}",
        "dataset.height=64",
        "dataset.width=96",
        "prepare.workers=2",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]
    script = textwrap.dedent(
        f"""
        import signal, sys
        signal.signal(signal.SIGINT, signal.default_int_handler)  # as from a terminal
        sys.argv = {argv!r}
        import fusion_depth.data.topview as topview
        real = topview.load_frame
        topview.load_frame = lambda *args, **kwargs: ({BUSY}, real(*args, **kwargs))[1]
        from fusion_depth.prepare.cli import main
        main()
        """
    )
    env = {**os.environ, "FUSION_DEPTH_CACHE": str(cache)}
    process = subprocess.Popen(
        [sys.executable, "-c", script], start_new_session=True, stderr=subprocess.PIPE, env=env
    )
    deadline = time.monotonic() + 120
    while not list(cache.glob("topview/*/train/0*.json")) and time.monotonic() < deadline:
        time.sleep(0.05)
    return process, cache, argv, env


def _no_leftovers_and_the_next_run_finishes(cache: Path, argv: list[str], env: dict) -> None:
    (folder,) = cache.glob("topview/*")
    hidden = [str(p.relative_to(folder)) for p in folder.rglob(".*")]
    assert hidden == [], f"left behind: {hidden}"
    assert not list(folder.glob("*/index.json"))  # stopped before the first split's end
    done = subprocess.run([sys.executable, "-m", "fusion_depth.prepare", *argv[1:]], env=env)
    assert done.returncode == 0
    assert len(list(folder.glob("*/index.json"))) == 3


@pytest.mark.slow
def test_ctrl_c_on_the_command_ends_within_2_s_in_one_line_leaving_nothing(tmp_path) -> None:
    """``python -m fusion_depth.prepare`` with two workers, each deep in a frame's C work, gets
    Ctrl-C: it exits within 2 s with status 130 and one line on stderr, no worker runs on, and
    the cache holds finished frames only (no temporary file, no claim); the next run finishes
    it."""
    process, cache, argv, env = _start_prepare_command(tmp_path)
    workers = _children(process.pid)
    time.sleep(0.3)  # into the next frames' C work
    os.killpg(process.pid, signal.SIGINT)
    pressed = time.monotonic()
    _, stderr = process.communicate(timeout=60)
    took = time.monotonic() - pressed
    lines = [line for line in stderr.decode().splitlines() if line.strip()]
    why = f"exit {process.returncode} after {took:.1f} s, stderr: {lines}"
    assert process.returncode == 130 and took < 2.0, why
    assert len(lines) == 1 and lines[0].startswith("prepare: interrupted"), why
    assert len(workers) == 2 and not [pid for pid in workers if _running(pid)], why
    _no_leftovers_and_the_next_run_finishes(cache, argv, env)


@pytest.mark.slow
def test_a_killed_worker_stops_the_command_in_one_line_leaving_nothing(tmp_path) -> None:
    """One worker is killed (as by the out-of-memory killer): prepare stops the other and says
    so in one line (status 1), leaving finished frames only."""
    process, cache, argv, env = _start_prepare_command(tmp_path)
    workers = _children(process.pid)
    os.kill(workers[0], signal.SIGKILL)
    _, stderr = process.communicate(timeout=60)
    lines = [line for line in stderr.decode().splitlines() if line.strip()]
    assert process.returncode == 1, lines
    # One line, as every error of a command about the user's input or machine.
    assert len(lines) == 1, lines
    assert lines[0].startswith("a prepare worker died (killed by SIGKILL"), lines
    assert "Traceback" not in stderr.decode(), lines
    assert not [pid for pid in workers if _running(pid)]
    _no_leftovers_and_the_next_run_finishes(cache, argv, env)
