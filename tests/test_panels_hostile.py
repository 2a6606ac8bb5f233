"""``report RECORD --panels OUT.png`` on hostile or odd ``test_panels.npz`` records: each is one
line on stderr naming the file and what was expected; a record whose figure would be too big is
refused from its arrays' headers, before any array is read; a full disk names the output."""

from __future__ import annotations

import errno
import os
import time
import tracemalloc
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from fusion_depth.data.visualize import PanelFrame, panel_figure, read_panel_frames
from fusion_depth.report import main

H, W = 16, 32


def _arrays(count: int = 2, height: int = H, width: int = W) -> dict[str, np.ndarray]:
    """The arrays of a small, valid panel-frames record."""
    gen = np.random.default_rng(0)
    return dict(
        image=gen.integers(0, 255, (count, 3, height, width), dtype=np.uint8),
        sparse=np.zeros((count, height, width), np.float32),
        prediction=gen.uniform(1, 40, (count, max(1, height // 2), max(1, width // 2))).astype(
            np.float32
        ),
        target=gen.uniform(1, 40, (count, height, width)).astype(np.float32),
        label=np.array(["day", "night", "fog"][:count] + ["x"] * max(0, count - 3)),
        depth_range=np.array([0.5, 80.0]),
    )


def _record(folder: Path, arrays: dict[str, np.ndarray]) -> Path:
    folder.mkdir(parents=True)
    path = folder / "test_panels.npz"
    np.savez_compressed(path, **arrays)
    return path


def _one_line_refusal(capsys, record: Path, out: Path) -> str:
    assert main([str(record.parent), "--panels", str(out)]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert "\n" not in err and "Traceback" not in err, err
    assert err.startswith("error: ") and str(record) in err, err
    assert not out.exists()
    return err


@pytest.mark.parametrize(
    "case",
    [
        "range 0 0",
        "range 1 inf",
        "range nan",
        "range reversed",
        "no frames",
        "0x0 image",
        "empty prediction",
    ],  # fmt: skip
)
def test_odd_ranges_and_empty_arrays_are_one_line_naming_the_file(tmp_path, capsys, case) -> None:
    arrays = _arrays()
    if case.startswith("range"):
        arrays["depth_range"] = {
            "range 0 0": np.array([0.0, 0.0]),
            "range 1 inf": np.array([1.0, np.inf]),
            "range nan": np.array([np.nan, 80.0]),
            "range reversed": np.array([80.0, 0.5]),
        }[case]
        expected = "expected 0 < min_depth < max_depth"
    elif case == "no frames":
        arrays = {k: (v if k == "depth_range" else v[:0]) for k, v in arrays.items()}
        expected = "no frames"
    elif case == "0x0 image":
        arrays = _arrays(height=0, width=0)
        expected = "expected at least 1"
    else:
        arrays["prediction"] = np.zeros((2, 8, 0), np.float32)
        expected = "expected at least 1"
    record = _record(tmp_path / "run", arrays)
    err = _one_line_refusal(capsys, record, tmp_path / "out.png")
    assert expected in err, err


def test_non_finite_values_and_a_math_like_label_draw_without_warnings(tmp_path, capsys) -> None:
    """NaN and infinite depths are drawn as 'no depth'; a label is drawn as plain text."""
    arrays = _arrays()
    arrays["target"][0, 0, :3] = [np.inf, np.nan, -np.inf]
    arrays["prediction"][1, 0, :2] = [np.nan, np.inf]
    arrays["sparse"][0, 1, :2] = [np.nan, -np.inf]
    arrays["label"] = np.array(["$x^$", "a$b"])
    record = _record(tmp_path / "run", arrays)
    out = tmp_path / "out.png"
    with _no_warnings():
        assert main([str(record.parent), "--panels", str(out)]) == 0
    assert capsys.readouterr().err == ""
    assert out.is_file()


class _no_warnings:
    def __enter__(self):
        import warnings

        self._catch = warnings.catch_warnings()
        self._catch.__enter__()
        warnings.simplefilter("error")
        return self

    def __exit__(self, *exc):
        return self._catch.__exit__(*exc)


# --- what a figure may cost is bounded before anything is read -------------------------------


def _write_declared(
    path: Path, arrays: dict[str, np.ndarray], declared: dict[str, tuple], data: bool = True
) -> None:
    """``arrays`` as an .npz whose members named in ``declared`` (name → shape, float32)
    declare that shape and hold as many zeros, streamed (never held in memory), or none
    (``data=False``: a cut file)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, array in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
                if name not in declared:
                    np.lib.format.write_array(f, array, allow_pickle=False)
                    continue
                dtype = np.uint8 if name == "image" else np.float32
                shape = declared[name]
                header = {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": shape}
                np.lib.format.write_array_header_1_0(f, header)
                left = int(np.prod(shape)) * np.dtype(dtype).itemsize if data else 0
                chunk = bytes(1 << 22)
                while left > 0:
                    f.write(chunk[: min(left, len(chunk))])
                    left -= len(chunk)


def _hostile(kind: str, folder: Path) -> Path:
    folder.mkdir(parents=True)
    path = folder / "test_panels.npz"
    if kind == "1x300000 image":  # the 5.6 KB record that asked for 68.7 GiB
        arrays = _arrays(count=1, height=1, width=300_000)
        np.savez_compressed(
            path, **{k: v if k in ("label", "depth_range") else v * 0 for k, v in arrays.items()}
        )
    elif kind == "200000-character label":  # 1.3 GiB
        arrays = _arrays(count=1)
        arrays["label"] = np.array(["x" * 200_000])
        np.savez_compressed(path, **arrays)
    elif kind == "6000x6000 prediction of zeros":  # the 20000² map asked for > 6 GiB
        _write_declared(path, _arrays(count=1), {"prediction": (1, 6000, 6000)})
    elif kind == "20000x20000 maps, cut":  # a few hundred bytes that ask for 4.4 GB
        maps = {"image": (1, 3, 20000, 20000), "sparse": (1, 20000, 20000)}
        maps["target"] = maps["sparse"]
        _write_declared(path, _arrays(count=1), maps, data=False)
    elif kind == "4000 frames":
        np.savez_compressed(path, **_arrays(count=4000, height=8, width=8))
    return path


@pytest.mark.parametrize(
    "kind",
    [
        "1x300000 image",
        "200000-character label",
        "6000x6000 prediction of zeros",
        "20000x20000 maps, cut",
        "4000 frames",
    ],
)
def test_a_figure_too_big_is_refused_before_any_array_is_read(
    tmp_path, capsys, monkeypatch, kind
) -> None:
    record = _hostile(kind, tmp_path / "run")
    assert record.stat().st_size < 8 << 20

    def never(*args, **kwargs):
        raise AssertionError(f"an array of {record} was read before its size was checked")

    monkeypatch.setattr(np.lib.npyio.NpzFile, "__getitem__", never)
    monkeypatch.setattr(np.lib.format, "read_array", never)
    tracemalloc.start()
    started = time.perf_counter()
    try:
        err = _one_line_refusal(capsys, record, tmp_path / "out.png")
        elapsed = time.perf_counter() - started
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert "limit" in err, err
    assert peak < 32 << 20, f"{peak / 2**20:.1f} MiB traced while refusing {kind}"
    assert elapsed < 5.0


def test_the_limits_name_themselves_and_a_real_sized_record_is_drawn(tmp_path, capsys) -> None:
    """Five nuScenes frames at full resolution (900x1600) fit the limits; labels at the limit
    are read, one character more is refused."""
    from fusion_depth.data.visualize import MAX_PANEL_LABEL_CHARS, MAX_PANEL_PIXELS

    assert MAX_PANEL_PIXELS >= 5 * 900 * 1600 * 5  # five columns of five frames
    arrays = _arrays(count=2)
    arrays["label"] = np.array(["d" * MAX_PANEL_LABEL_CHARS, "n"])
    frames, *_ = read_panel_frames(_record(tmp_path / "ok", arrays))
    assert [len(f.label) for f in frames] == [MAX_PANEL_LABEL_CHARS, 1]
    arrays["label"] = np.array(["d" * (MAX_PANEL_LABEL_CHARS + 1), "n"])
    with pytest.raises(ValueError, match=f"at most {MAX_PANEL_LABEL_CHARS} characters"):
        read_panel_frames(_record(tmp_path / "long", arrays))


@pytest.mark.parametrize(
    "count,height,width,label", [(1, 1, 1, ""), (2, 16, 32, "night"), (3, 130, 50, "x" * 40)]
)
def test_the_bound_holds_the_figure_drawn(count, height, width, label) -> None:
    """The refusal is decided by panel_figure_bound: it must hold every figure drawn, closely."""
    from fusion_depth.data.visualize import panel_figure_bound

    gen = torch.Generator().manual_seed(0)
    frames = [
        PanelFrame(
            image=torch.rand(3, height, width, generator=gen),
            sparse=torch.zeros(height, width),
            prediction=torch.rand(height, width, generator=gen) * 40 + 1,
            target=torch.rand(height, width, generator=gen) * 40 + 1,
            label=label,
        )
        for _ in range(count)
    ]
    drawn_rows, drawn_columns = panel_figure(frames, 0.5, 80.0).shape[:2]
    rows, columns = panel_figure_bound(count, height, width, len(label))
    assert drawn_rows <= rows <= drawn_rows + 40
    assert drawn_columns <= columns <= drawn_columns + 400


# --- a full disk names the file -----------------------------------------------------------------


def _disk_full(monkeypatch) -> None:
    """The file system fills up as the figure is flushed (what ENOSPC on fsync looks like)."""

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "fsync", full)


def test_panels_on_a_full_disk_names_the_output_and_keeps_the_old_one(
    tmp_path, capsys, monkeypatch
) -> None:
    record = _record(tmp_path / "run", _arrays())
    out = tmp_path / "figs" / "panels.png"
    assert main([str(record.parent), "--panels", str(out)]) == 0
    before = out.read_bytes()
    capsys.readouterr()
    _disk_full(monkeypatch)
    assert main([str(record.parent), "--panels", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    monkeypatch.undo()
    assert "\n" not in err and str(out) in err and "the disk is full" in err, err
    assert out.read_bytes() == before
    assert sorted(p.name for p in out.parent.iterdir()) == ["panels.png"]


def test_plot_on_a_full_disk_names_the_output(tmp_path, capsys, monkeypatch) -> None:
    from test_report import _write_run

    for seed in (1, 2):
        _write_run(tmp_path / "sweep", f"rgb-{seed}", "rgb", "l1", seed, rmse=5.0 + seed)
    out = tmp_path / "figs" / "plot.png"
    _disk_full(monkeypatch)
    assert main([str(tmp_path / "sweep"), "--plot", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    monkeypatch.undo()
    assert "\n" not in err and str(out) in err and "the disk is full" in err, err
    assert not out.parent.exists() or list(out.parent.iterdir()) == []
