"""``python -m fusion_depth.predict``: depth PNGs, .npy, visualisations, skipping bad inputs.

Checkpoints are built by hand (an untrained DepthNet saved the way training saves it), so no
test trains.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import REPO, compose_config, run_module
from hydra.core.global_hydra import GlobalHydra

from fusion_depth.data.depth_io import read_depth_png, read_rgb, write_depth_png, write_rgb_png
from fusion_depth.data.visualize import (
    MIN_COLORBAR_HEIGHT,
    colorbar_ticks,
    colorize_depth,
    depth_colorbar,
    with_colorbar,
)
from fusion_depth.models.inference import predict_depth
from fusion_depth.predict.cli import predict
from fusion_depth.predict.files import (
    PredictSummary,
    list_images,
    predict_file,
    predict_folder,
    predict_split,
)
from fusion_depth.runner.checkpoints import load_model

MIN_DEPTH, MAX_DEPTH = 0.5, 80.0
H, W = 64, 96
PNG_STEP = 1 / 256


@pytest.fixture(scope="module")
def fusion_model(checkpoints: dict[str, Path]):
    return load_model(checkpoints["concat"])


@pytest.fixture(scope="module")
def rgb_model(checkpoints: dict[str, Path]):
    return load_model(checkpoints["rgb"])


def _write_inputs(
    root: Path, sizes: dict[str, tuple[int, int]], suffix: str = ".png"
) -> tuple[Path, Path]:
    """``root/images/<stem><suffix>`` and ``root/sparse/<stem>.png`` with a few returns each."""
    rng = np.random.default_rng(0)
    images, sparse = root / "images", root / "sparse"
    for stem, (height, width) in sizes.items():
        image = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
        if suffix == ".png":
            write_rgb_png(images / f"{stem}.png", image)
        else:
            images.mkdir(parents=True, exist_ok=True)
            from PIL import Image

            Image.fromarray(image).save(images / f"{stem}{suffix}")
        points = np.zeros((height, width), np.float32)
        rows, cols = rng.integers(0, height, 30), rng.integers(0, width, 30)
        points[rows, cols] = rng.uniform(2.0, 60.0, 30)
        write_depth_png(sparse / f"{stem}.png", points)
    return images, sparse


def _colorbar_width(height: int) -> int:
    return depth_colorbar(height, MIN_DEPTH, MAX_DEPTH).shape[1]


def _assert_round_trip(png: Path, depth: np.ndarray) -> None:
    """The PNG holds the prediction rounded to 1/256 m: at most half a step off."""
    stored = read_depth_png(png)
    assert stored.shape == depth.shape
    assert np.abs(stored - depth).max() <= PNG_STEP / 2 + 1e-5
    assert np.abs(stored - depth).max() < PNG_STEP


def test_folder_png_round_trips_to_the_predicted_metres(fusion_model, tmp_path: Path) -> None:
    # Two sizes, batched two at a time: batches must only hold images of one size.
    sizes = {"a": (H, W), "b": (H, W), "c": (50, 70)}
    images, sparse = _write_inputs(tmp_path, sizes)
    out = tmp_path / "out"
    summary = predict_folder(
        fusion_model, images, out, sparse, npy=True, batch_size=2, progress=False
    )

    assert isinstance(summary, PredictSummary) and summary.ok
    assert [p.name for p in summary.written] == ["a.png", "b.png", "c.png"]
    for stem, (height, width) in sizes.items():
        depth = np.load(out / f"{stem}.npy")
        assert depth.dtype == np.float32 and depth.shape == (height, width)
        assert MIN_DEPTH - 1e-4 <= depth.min() and depth.max() <= MAX_DEPTH + 1e-4
        _assert_round_trip(out / f"{stem}.png", depth)
        viz = read_rgb(out / f"{stem}.viz.png")  # no ground truth: 3 tiles + colour bar
        assert viz.shape == (height, 3 * width + _colorbar_width(height), 3)
        if stem != "b":
            continue
        # The batched prediction (b went with a) is the one of the image on its own.
        image = torch.from_numpy(read_rgb(images / f"{stem}.png").copy()).permute(2, 0, 1)
        alone = predict_depth(
            fusion_model.net,
            image[None].float() / 255,
            torch.from_numpy(read_depth_png(sparse / f"{stem}.png"))[None, None],
        )[0, 0].numpy()
        np.testing.assert_allclose(depth, alone, atol=1e-3)
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary files left


def test_a_bad_input_is_skipped_by_name_and_the_rest_written(
    fusion_model, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    images, sparse = _write_inputs(tmp_path, {"a": (H, W), "b": (H, W), "c": (H, W)})
    (images / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    write_depth_png(sparse / "c.png", np.ones((H // 2, W), np.float32))  # wrong size
    (images / "d.jpg").write_bytes(b"")  # empty file
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="fusion_depth.predict"):
        summary = predict_folder(fusion_model, images, out, sparse, progress=False)

    assert [p.name for p in summary.written] == ["a.png"]
    assert [s.source for s in summary.skipped] == [
        str(images / n) for n in ("b.png", "c.png", "d.jpg")
    ]
    assert not summary.ok and summary.total == 4
    for name in ("b.png", "c.png", "d.jpg"):
        assert f"skipped {images / name}: " in caplog.text
    assert "sparse depth is 32×96" in caplog.text
    assert "predicted 1 of 4 inputs" in caplog.text and str(images / "d.jpg") in summary.line()
    assert sorted(p.name for p in out.iterdir()) == ["a.png", "a.viz.png"]


def test_a_1x1_image_between_good_ones_gets_its_outputs_and_so_do_they(
    fusion_model, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    images, sparse = _write_inputs(tmp_path, {"a": (H, W), "b": (1, 1), "c": (H, W)})
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="fusion_depth.predict"):
        summary = predict_folder(fusion_model, images, out, sparse, npy=True, progress=False)

    assert summary.ok and [p.name for p in summary.written] == ["a.png", "b.png", "c.png"]
    assert "predicted 3 of 3 inputs" in caplog.text and "skipped" not in caplog.text
    for stem in "ac":
        _assert_round_trip(out / f"{stem}.png", np.load(out / f"{stem}.npy"))
        assert read_rgb(out / f"{stem}.viz.png").shape == (H, 3 * W + _colorbar_width(H), 3)
    tiny = np.load(out / "b.npy")
    assert tiny.shape == (1, 1) and MIN_DEPTH - 1e-4 <= tiny[0, 0] <= MAX_DEPTH + 1e-4
    _assert_round_trip(out / "b.png", tiny)
    # Three 1-pixel tiles padded with black rows up to the colour bar's minimum height.
    viz = read_rgb(out / "b.viz.png")
    bar = _colorbar_width(MIN_COLORBAR_HEIGHT)
    assert viz.shape == (MIN_COLORBAR_HEIGHT, 3 + bar, 3)
    np.testing.assert_array_equal(viz[0, 0], read_rgb(images / "b.png")[0, 0])
    np.testing.assert_array_equal(
        viz[0, 2],
        colorize_depth(tiny, fusion_model.net.min_depth, fusion_model.net.max_depth)[0, 0],
    )
    assert not viz[1:, :3].any() and viz[:, 3:].any()


def test_no_output_replaces_another_output_of_the_run(
    fusion_model, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: with ``x.png`` and ``x.viz.png`` in the folder, the depth PNG of the input
    ``x.viz.png`` replaced the visualisation of ``x.png``, and the run said "predicted 2 of 2".
    Now the later input whose outputs would take another's names is skipped in one line naming
    the other, and every output written is the one of its own input."""
    images, sparse = _write_inputs(tmp_path, {"x": (H, W), "x.viz": (H, W), "y": (H, W)})
    write_rgb_png(images / "y.jpg", read_rgb(images / "y.png"))  # first by name: takes y.png
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="fusion_depth.predict"):
        summary = predict_folder(fusion_model, images, out, sparse, npy=True, progress=False)

    assert [p.name for p in summary.written] == ["x.png", "y.png"]
    assert summary.total == 4 and not summary.ok
    for name, other in (("x.viz.png", "x.png"), ("y.png", "y.jpg")):
        (line,) = [
            r.getMessage() for r in caplog.records if f"skipped {images / name}" in r.getMessage()
        ]
        assert "\n" not in line and f"of {other}" in line
    # x.viz.png is x.png's visualisation (8-bit colour, image | sparse | prediction | colour
    # bar), not a depth PNG; each depth PNG is its own input's prediction.
    assert read_rgb(out / "x.viz.png").shape == (H, 3 * W + _colorbar_width(H), 3)
    for stem in "xy":
        _assert_round_trip(out / f"{stem}.png", np.load(out / f"{stem}.npy"))
    assert sorted(p.name for p in out.iterdir()) == sorted(
        f"{s}{suffix}" for s in "xy" for suffix in (".png", ".npy", ".viz.png")
    )
    # Without visualisations nothing collides: both x inputs are predicted.
    summary = predict_folder(
        fusion_model, images, tmp_path / "plain", sparse, visualize=False, limit=2, progress=False
    )
    assert summary.ok and [p.name for p in summary.written] == ["x.png", "x.viz.png"]


@pytest.fixture(scope="module")
def too_many_pixels(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 9000×9000 PNG (81 MP, under Pillow's limit): 80 KB on disk, 243 MB decoded, and tens
    of GB for the network at full resolution."""
    from PIL import Image

    path = tmp_path_factory.mktemp("huge") / "huge.png"
    Image.new("RGB", (9000, 9000)).save(path, compress_level=1)
    return path


def _never_decoded(monkeypatch: pytest.MonkeyPatch, path: Path) -> None:
    """Reading ``path``'s pixels fails the test: the bound is checked from the header."""
    import fusion_depth.predict.files as module

    real = module.read_rgb

    def read_rgb(file, *args, **kwargs):
        assert Path(file) != path, f"{path} was decoded"
        return real(file, *args, **kwargs)

    monkeypatch.setattr(module, "read_rgb", read_rgb)


def test_an_image_too_big_for_memory_is_refused_in_one_line_alone_or_in_a_folder(
    rgb_model, too_many_pixels: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before: given alone, an 81 MP image was decoded and sent to the network (an allocator
    traceback, or the machine's memory exhausted); in a folder it was skipped only once the
    network failed. Now both refuse it from its header, naming the file, its size and the
    limit, and a folder predicts the rest."""
    _never_decoded(monkeypatch, too_many_pixels)
    out = tmp_path / "out"
    with pytest.raises(ValueError) as err:
        predict_file(rgb_model, too_many_pixels, out)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{too_many_pixels}: ")
    assert "9000×9000" in message and "max_pixels=16777216" in message
    assert not out.exists() or not list(out.iterdir())

    folder = tmp_path / "images"
    write_rgb_png(folder / "a.png", np.full((H, W, 3), 128, np.uint8))
    (folder / "huge.png").symlink_to(too_many_pixels)
    summary = predict_folder(rgb_model, folder, out, progress=False)
    assert [p.name for p in summary.written] == ["a.png"]
    (skipped,) = summary.skipped
    assert skipped.source == str(folder / "huge.png") and "9000×9000" in skipped.reason
    # The bound is an option: a smaller one refuses a smaller image; null takes any size.
    with pytest.raises(ValueError, match=r"a\.png: an image of 96×64 pixels.*max_pixels=1000"):
        predict_file(rgb_model, folder / "a.png", tmp_path / "small", max_pixels=1000)
    predict_file(rgb_model, folder / "a.png", tmp_path / "any", max_pixels=None)
    with pytest.raises(ValueError, match=r"max_pixels=0: expected null \(any size\) or"):
        predict_file(rgb_model, folder / "a.png", tmp_path / "any", max_pixels=0)


@pytest.mark.slow
def test_the_command_refuses_an_image_too_big_for_memory_in_one_line(
    checkpoints, too_many_pixels: Path, tmp_path: Path
) -> None:
    result = run_module(
        [
            "fusion_depth.predict",
            f"ckpt_path={checkpoints['rgb']}",
            f"input={too_many_pixels}",
            f"output_dir={tmp_path / 'out'}",
            f"hydra.run.dir={tmp_path / 'run'}",
            "device=cpu",
        ],
        cwd=REPO,
        timeout=300,
    )
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 1 and len(lines) == 1, result.stderr
    assert lines[0].startswith(f"{too_many_pixels}: an image of 9000×9000 pixels")
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


def test_with_colorbar_pads_a_short_panel_and_keeps_a_tall_one() -> None:
    panel = np.full((1, 5, 3), 200, np.uint8)
    out = with_colorbar(panel, MIN_DEPTH, MAX_DEPTH)
    bar = depth_colorbar(MIN_COLORBAR_HEIGHT, MIN_DEPTH, MAX_DEPTH)
    assert out.shape == (MIN_COLORBAR_HEIGHT, 5 + bar.shape[1], 3)
    assert (out[0, :5] == 200).all() and not out[1:, :5].any()
    np.testing.assert_array_equal(out[:, 5:], bar)
    tall = np.zeros((H, 7, 3), np.uint8)
    assert with_colorbar(tall, MIN_DEPTH, MAX_DEPTH).shape == (H, 7 + _colorbar_width(H), 3)


def test_a_failure_writing_one_input_is_a_skip_and_leaves_no_outputs_of_it(
    fusion_model, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    images, sparse = _write_inputs(tmp_path, {"a": (H, W), "b": (H, W), "c": (H, W)})
    out = tmp_path / "out"
    (out / "b.viz.png").mkdir(parents=True)  # a folder where b's visualisation must go
    with caplog.at_level(logging.INFO, logger="fusion_depth.predict"):
        summary = predict_folder(fusion_model, images, out, sparse, npy=True, progress=False)

    assert [p.name for p in summary.written] == ["a.png", "c.png"]
    assert [s.source for s in summary.skipped] == [str(images / "b.png")]
    assert summary.skipped[0].reason.startswith("writing its outputs failed (IsADirectoryError")
    assert f"skipped {images / 'b.png'}: writing its outputs failed" in caplog.text
    assert "predicted 2 of 3 inputs" in caplog.text and not summary.ok
    # b's depth PNG and .npy were written before the visualisation failed: removed again.
    assert sorted(p.name for p in out.iterdir()) == [
        "a.npy",
        "a.png",
        "a.viz.png",
        "b.viz.png",
        "c.npy",
        "c.png",
        "c.viz.png",
    ]
    assert (out / "b.viz.png").is_dir()


def _failing_on_white(monkeypatch: pytest.MonkeyPatch, always: bool = False) -> list[int]:
    """The network raises (as on running out of memory) for any batch holding an all-white
    image, or for every batch; returns the batch sizes it was called with."""
    import fusion_depth.predict.files as module

    real, calls = module.predict_depth, []

    def predict_depth(net, images, sparse=None, **kwargs):
        calls.append(len(images))
        if always or (images.flatten(1) == 1).all(dim=1).any():
            raise RuntimeError("CUDA out of memory. Tried to allocate 9.00 GiB\nmore details")
        return real(net, images, sparse, **kwargs)

    monkeypatch.setattr(module, "predict_depth", predict_depth)
    return calls


def test_a_network_failure_on_one_image_skips_only_that_image(
    fusion_model, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    images, sparse = _write_inputs(tmp_path, {"a": (H, W), "b": (H, W), "c": (H, W)})
    write_rgb_png(images / "b.png", np.full((H, W, 3), 255, np.uint8))
    calls = _failing_on_white(monkeypatch)
    out = tmp_path / "out"
    summary = predict_folder(fusion_model, images, out, sparse, batch_size=2, progress=False)

    # The batch (a, b) failed, then a and b went alone; c was its own batch.
    assert calls == [2, 1, 1, 1]
    assert [p.name for p in summary.written] == ["a.png", "c.png"]
    assert [(s.source, s.reason) for s in summary.skipped] == [
        (
            str(images / "b.png"),
            "prediction failed (RuntimeError: CUDA out of memory. Tried to allocate 9.00 GiB)",
        )
    ]
    alone = predict_file(fusion_model, images / "a.png", tmp_path / "alone", sparse / "a.png")
    np.testing.assert_allclose(
        read_depth_png(out / "a.png"), read_depth_png(tmp_path / "alone" / "a.png")
    )
    assert alone.shape == (H, W)


def test_a_network_failing_on_every_input_stops_the_run(
    fusion_model, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    images, sparse = _write_inputs(tmp_path, {s: (H, W) for s in "abcde"})
    calls = _failing_on_white(monkeypatch, always=True)
    with pytest.raises(RuntimeError, match=r"failed on 3 inputs in a row, the last .*c\.png"):
        predict_folder(fusion_model, images, tmp_path / "out", sparse, progress=False)
    assert calls == [1, 1, 1]  # d and e were never tried


def test_an_output_dir_that_is_a_file_fails_before_any_prediction(
    fusion_model, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    images, sparse = _write_inputs(tmp_path, {"a": (H, W)})
    calls = _failing_on_white(monkeypatch)
    (tmp_path / "taken").write_text("not a folder")
    with pytest.raises(NotADirectoryError, match=r"output_dir=.*taken: a file, expected a folder"):
        predict_folder(fusion_model, images, tmp_path / "taken", sparse, progress=False)
    assert calls == []


def test_single_file(fusion_model, tmp_path: Path) -> None:
    images, sparse = _write_inputs(tmp_path, {"frame": (H, W)}, suffix=".jpg")
    out = tmp_path / "out"
    depth = predict_file(fusion_model, images / "frame.jpg", out, sparse / "frame.png")

    assert depth.shape == (H, W)
    _assert_round_trip(out / "frame.png", depth)
    assert not (out / "frame.npy").exists()  # npy is opt-in
    # A ground truth given: the 4th tile appears.
    gt = tmp_path / "gt.png"
    write_depth_png(gt, np.full((H, W), 10.0, np.float32))
    predict_file(fusion_model, images / "frame.jpg", out, sparse / "frame.png", gt, npy=True)
    assert read_rgb(out / "frame.viz.png").shape == (H, 4 * W + _colorbar_width(H), 3)
    np.testing.assert_allclose(np.load(out / "frame.npy"), depth, atol=1e-5)


def test_split_panels_show_the_ground_truth(fusion_model, tmp_path: Path) -> None:
    out = tmp_path / "out"
    summary = predict_split(fusion_model, "test", out, limit=3, batch_size=2, progress=False)

    assert summary.ok and summary.total == 3
    assert [p.name for p in summary.written] == [f"test_{i:06d}.png" for i in range(3)]
    viz = read_rgb(out / "test_000000.viz.png")
    assert viz.shape == (H, 4 * W + _colorbar_width(H), 3)
    assert viz[:, 3 * W : 4 * W].any()  # the ground-truth tile is not empty
    _assert_round_trip(out / "test_000002.png", read_depth_png(out / "test_000002.png"))


def test_rgb_checkpoint_needs_no_sparse_and_ignores_it(rgb_model, tmp_path: Path) -> None:
    images, sparse = _write_inputs(tmp_path, {"a": (H, W)})
    without = predict_file(rgb_model, images / "a.png", tmp_path / "without", visualize=False)
    with_sparse = predict_file(rgb_model, images / "a.png", tmp_path / "with", sparse / "a.png")
    np.testing.assert_array_equal(without, with_sparse)
    assert not (tmp_path / "without" / "a.viz.png").exists()
    summary = predict_folder(rgb_model, images, tmp_path / "folder", progress=False)
    assert summary.ok and [p.name for p in summary.written] == ["a.png"]


def test_fusion_checkpoint_without_sparse_is_a_clear_error(fusion_model, tmp_path: Path) -> None:
    images, _ = _write_inputs(tmp_path, {"a": (H, W)})
    with pytest.raises(ValueError, match=r"sparse=null: ckpt_path=.*concat\.ckpt.*fusion=concat"):
        predict_folder(fusion_model, images, tmp_path / "out", progress=False)
    with pytest.raises(ValueError, match="sparse=null"):
        predict_file(fusion_model, images / "a.png", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_inputs_are_checked_before_any_work(fusion_model, tmp_path: Path) -> None:
    images, sparse = _write_inputs(tmp_path, {"a": (H, W)})
    with pytest.raises(FileNotFoundError, match=r"input=.*nowhere: no such folder"):
        predict_folder(fusion_model, tmp_path / "nowhere", tmp_path / "out", sparse)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"input=.*empty: no images in it"):
        predict_folder(fusion_model, tmp_path / "empty", tmp_path / "out", sparse)
    with pytest.raises(ValueError, match="would overwrite the inputs"):
        predict_folder(fusion_model, images, images, sparse)
    with pytest.raises(ValueError, match="would overwrite the input"):
        predict_file(fusion_model, images / "a.png", images, sparse)
    with pytest.raises(ValueError, match=r"sparse=.*a\.png: with a folder input"):
        predict_folder(fusion_model, images, tmp_path / "out", sparse / "a.png")
    with pytest.raises(ValueError, match=r"input=split:dev: expected a split of"):
        predict_split(fusion_model, "dev", tmp_path / "out")
    assert list_images(images) == [images / "a.png"]


def test_colorbar_matches_the_panels_scale() -> None:
    bar = depth_colorbar(200, MIN_DEPTH, MAX_DEPTH)
    ticks = colorbar_ticks(200, MIN_DEPTH, MAX_DEPTH, min_gap=16)
    depths = [d for d, _ in ticks]
    assert depths[0] == MAX_DEPTH and depths[-1] == MIN_DEPTH and 1.0 in depths  # far on top
    strip = bar[:, 2]  # the colour strip's first column
    for depth, row in ticks:
        expected = colorize_depth(np.array([[depth]], np.float32), MIN_DEPTH, MAX_DEPTH)[0, 0]
        assert np.abs(strip[int(round(row))].astype(int) - expected).max() <= 3
    assert bar[:, -30:].max() > 200  # white labels were drawn


def _compose_predict(overrides: list[str], run_dir: Path):
    return compose_config(overrides, run_dir, config_name="predict")


def test_config_with_another_dataset_for_a_split(checkpoints, tmp_path: Path) -> None:
    cfg = _compose_predict(
        [
            f"ckpt_path={checkpoints['rgb']}",
            "input=split:val",
            "dataset=procedural",
            "dataset.width=128",
            "dataset.reader.num_val=2",
            "npy=true",
            "device=cpu",
        ],
        tmp_path / "run",
    )
    try:
        summary = predict(cfg)
    finally:
        GlobalHydra.instance().clear()
    out = tmp_path / "run" / "predictions"  # default output_dir: inside the Hydra run dir
    assert summary.ok and summary.output_dir == out
    assert np.load(out / "val_000001.npy").shape == (H, 128)  # the chosen dataset's size
    assert read_rgb(out / "val_000001.viz.png").shape == (H, 4 * 128 + _colorbar_width(H), 3)


@pytest.mark.slow
def test_entry_point_writes_outputs_and_fails_on_skips(checkpoints, tmp_path: Path) -> None:
    # b cannot be read; the 1x1 image c after it is predicted like a.
    images, sparse = _write_inputs(tmp_path, {"a": (H, W), "b": (H, W), "c": (1, 1)})
    (images / "b.png").write_bytes(b"garbage")
    out = tmp_path / "out"
    result = run_module(
        [
            "fusion_depth.predict",
            f"ckpt_path={checkpoints['concat']}",
            f"input={images}",
            f"sparse={sparse}",
            f"output_dir={out}",
            f"hydra.run.dir={tmp_path / 'run'}",
            "device=cpu",
        ],
        cwd=REPO,
        timeout=300,
    )
    text = result.stdout + result.stderr
    assert result.returncode == 1, text
    assert f"skipped {images / 'b.png'}: " in text
    assert f"predicted 2 of 3 inputs into {out}; skipped 1: {images / 'b.png'}" in text
    assert text.count("skipped ") == 2  # b's line and the summary's
    for stem in "ac":
        assert (out / f"{stem}.png").is_file() and (out / f"{stem}.viz.png").is_file()
    assert read_depth_png(out / "c.png").shape == (1, 1)
    assert not (out / "b.png").exists()
    assert (tmp_path / "run" / "predict.log").is_file()
