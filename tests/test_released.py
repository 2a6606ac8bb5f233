"""Released checkpoints scored by the platform (``evaluate released=radarnet``), the RadarNet
layout reader (``dataset=radarnet_layout``) and ``report --published``.

The released files cannot be downloaded here: the tests write files in their exact layout
(the authors' ``save_model``: a dict of ``DataParallel`` state dicts) with random weights, in the
shipped configuration, and check that the platform's scores are the pipeline's own, run
directly on the same files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import run_module
from PIL import Image

from fusion_depth.data.radarnet_layout import RadarNetLayout
from fusion_depth.models.radarnet_released import FusionNet, RadarNetV1, ReleasedRadarNet
from fusion_depth.models.released import radarnet_frame_points


def write_released(net: RadarNetV1 | FusionNet, path: Path) -> Path:
    """``net`` as the authors' save_model writes it after data_parallel(): module.-prefixed."""
    names = (
        ("radarnet_encoder_state_dict", "radarnet_decoder_state_dict")
        if isinstance(net, RadarNetV1)
        else ("encoder_state_dict", "decoder_state_dict")
    )
    parts = (net.encoder, net.decoder)
    state = {
        name: {f"module.{k}": v for k, v in part.state_dict().items()}
        for name, part in zip(names, parts, strict=True)
    }
    torch.save({**state, "train_step": 195000}, path)
    return path


def write_layout(root: Path, frames: list[dict], split: str = "test") -> None:
    """RadarNet's setup output for ``frames`` (image uint8 HxWx3, radar (N, 3) float64, lidar
    float metres HxW), with lists of paths relative to ``root``, as its scripts write them."""
    folder, prefix = {"test": ("testing/nuscenes", "nuscenes_test")}[split]
    lists: dict[str, list[str]] = {"image": [], "radar": [], "lidar": []}
    for i, frame in enumerate(frames):
        name = f"n008-2018-08-01-15-16-36-0400__CAM_FRONT__{1533151603512404 + i}"
        paths = {
            "image": f"data/nuscenes/samples/CAM_FRONT/{name}.jpg",
            "radar": f"data/nuscenes_derived_test/radar_points/scene_0/CAM_FRONT/{name}.npy",
            "lidar": f"data/nuscenes_derived_test/lidar/scene_0/CAM_FRONT/{name}.png",
        }
        for rel in paths.values():
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(frame["image"]).save(root / paths["image"], quality=90)
        np.save(root / paths["radar"], frame["radar"])
        Image.fromarray(np.uint32(frame["lidar"] * 256.0).astype(np.uint16)).save(
            root / paths["lidar"]
        )
        for role, rel in paths.items():
            lists[role].append(rel)
    (root / folder).mkdir(parents=True, exist_ok=True)
    for role, paths in lists.items():
        (root / folder / f"{prefix}_{role}.txt").write_text("\n".join(paths) + "\n")


def make_frame(rng: np.random.Generator, height: int, width: int, points: int) -> dict:
    """A frame: smooth image, radar on distinct whole pixels (row-major, as np.nonzero gives
    them), lidar on a few thousand pixels."""
    yy, xx = np.mgrid[0:height, 0:width]
    image = np.stack(
        [(xx * 255 // width), (yy * 255 // height), ((xx + yy) * 7) % 256], axis=-1
    ).astype(np.uint8)
    flat = np.sort(rng.choice((height - 4) * (width - 4), points, replace=False))
    rows, cols = flat // (width - 4) + 2, flat % (width - 4) + 2
    radar = np.stack([cols, rows, rng.uniform(2.0, 90.0, points)], axis=1).astype(np.float64)
    lidar = np.zeros((height, width))
    pick = rng.choice(height * width, min(3000, height * width // 4), replace=False)
    lidar.flat[pick] = rng.uniform(1.5, 95.0, len(pick))
    return {"image": image, "radar": radar, "lidar": lidar}


# --- the authors' radar points from the platform's rows -----------------------------------------


def test_frame_points_are_their_setups_one_per_pixel_row_major_inside_the_margin() -> None:
    """Rows come nearest first with continuous u, v: back to whole pixels, one per pixel (the
    nearer), ordered by row then column, without those within a pixel of the border."""
    rows = torch.tensor(
        [
            # u,     v,    depth, rcs, vel, valid   (nearest first, as point_rows sorts them)
            [10.2, 20.4, 3.0, 0, 0, 1],
            [10.4, 19.6, 4.0, 0, 0, 1],  # the same pixel (20, 10), farther: dropped
            [5.0, 3.0, 5.0, 0, 0, 1],  # row 3 comes before row 20
            [0.9, 30.0, 6.0, 0, 0, 1],  # u <= 1: outside their margin
            [99.2, 30.0, 7.0, 0, 0, 1],  # u >= W - 1 (W = 100): outside
            [50.0, 59.0, 8.0, 0, 0, 1],  # v >= H - 1 (H = 60): outside
            [50.0, 40.0, 0.9, 0, 0, 1],  # depth <= 1 m: outside
            [60.6, 20.0, 9.0, 0, 0, 1],  # row 20, after column 10
            [0.0, 0.0, 0.0, 0, 0, 0],  # padding
        ]
    )
    points = radarnet_frame_points(rows, 60, 100)
    expected = [[5.0, 3.0, 5.0], [10.0, 20.0, 3.0], [61.0, 20.0, 9.0]]
    assert points.tolist() == expected


# --- the reader of their files ------------------------------------------------------------------


def test_the_layout_is_served_as_the_files_are(tmp_path: Path) -> None:
    """At the files' own size: the image's pixels, the radar file's rows as radar_points (and
    in sparse), the lidar PNG as depth and as full-resolution points."""
    rng = np.random.default_rng(0)
    frames = [make_frame(rng, 90, 160, 12) for _ in range(2)]
    write_layout(tmp_path / "radarnet", frames)
    reader = RadarNetLayout(
        "test", tmp_path / "radarnet", tmp_path / "cache", 90, 160, size_multiple=1
    )
    assert len(reader) == 2
    for sample, frame in zip(reader, frames, strict=True):
        served = sample["radar_points"].numpy()
        served = served[served[:, 5] > 0]
        assert sorted(map(tuple, served[:, :3].round(4).tolist())) == sorted(
            map(tuple, frame["radar"].astype(np.float32).round(4).tolist())
        )
        sparse = sample["sparse"][0].numpy()
        assert sparse[frame["radar"][:, 1].astype(int), frame["radar"][:, 0].astype(int)] == (
            pytest.approx(frame["radar"][:, 2].astype(np.float32), abs=1 / 256)
        )
        expected = np.uint32(frame["lidar"] * 256.0) / 256.0
        np.testing.assert_array_equal(sample["depth"][0].numpy(), expected)
        rows = sample["depth_points"].numpy()
        rows = rows[rows[:, 2] > 0]
        assert len(rows) == int((expected > 0).sum())
        np.testing.assert_array_equal(
            rows[:, 2], expected[rows[:, 0].astype(int), rows[:, 1].astype(int)]
        )


def test_the_image_is_the_jpeg_as_decoded(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    write_layout(tmp_path / "r", [make_frame(rng, 64, 96, 5)])
    reader = RadarNetLayout("test", tmp_path / "r", tmp_path / "cache", 64, 96, size_multiple=1)
    jpeg = next((tmp_path / "r/data/nuscenes/samples/CAM_FRONT").glob("*.jpg"))
    decoded = np.asarray(Image.open(jpeg).convert("RGB")).astype(np.float32) / 255.0
    np.testing.assert_array_equal(reader[0]["image"].permute(1, 2, 0).numpy(), decoded)


def test_lists_of_other_lengths_or_a_missing_list_are_one_line(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    write_layout(tmp_path / "r", [make_frame(rng, 64, 96, 5) for _ in range(2)])
    radar_list = tmp_path / "r/testing/nuscenes/nuscenes_test_radar.txt"
    radar_list.write_text(radar_list.read_text().splitlines()[0] + "\n")
    with pytest.raises(ValueError, match=r"nuscenes_test_radar.txt: 1 paths, but .* has 2") as err:
        RadarNetLayout("test", tmp_path / "r", tmp_path / "cache", 64, 96, size_multiple=1)
    assert "\n" not in str(err.value)
    radar_list.unlink()
    with pytest.raises(FileNotFoundError, match="nuscenes_test_radar.txt: no such list"):
        RadarNetLayout("test", tmp_path / "r", tmp_path / "cache", 64, 96, size_multiple=1)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="nuscenes_test_image.txt: no such list"):
        RadarNetLayout("test", tmp_path / "empty", tmp_path / "cache", 64, 96, size_multiple=1)


# --- evaluate released=radarnet, end to end -----------------------------------------------------


def _per_image_mae(pred: np.ndarray, gt: np.ndarray, cap: float) -> float:
    valid = (gt > 0) & (gt < cap)
    return float(np.abs(pred[valid] - gt[valid]).mean())


@pytest.mark.slow
def test_evaluate_scores_the_released_pipeline_and_report_puts_the_paper_beside_it(
    tmp_path: Path,
) -> None:
    """The command the docs give, on files in the released layout (shipped configuration,
    random weights) and two 900×1600 frames in RadarNet's layout: its MAE per cap is the one
    of the two stages run directly on the same files, and report --published gives the row."""
    torch.manual_seed(0)
    association, fusion = RadarNetV1().eval(), FusionNet().eval()
    weights = tmp_path / "weights"
    weights.mkdir()
    write_released(association, weights / "model-195000.pth")
    write_released(fusion, weights / "model-815000.pth")
    rng = np.random.default_rng(3)
    frames = [make_frame(rng, 900, 1600, 3) for _ in range(2)]
    write_layout(tmp_path / "radarnet", frames)
    out = tmp_path / "scored"
    result = run_module(
        [
            "fusion_depth.evaluate",
            "released=radarnet",
            "dataset=radarnet_layout",
            f"dataset.root={tmp_path / 'radarnet'}",
            f"released.association_weights={weights / 'model-195000.pth'}",
            f"released.fusion_weights={weights / 'model-815000.pth'}",
            f"paths.cache_dir={tmp_path / 'cache'}",
            f"hydra.run.dir={out}",
        ],
        cwd=Path(__file__).parents[1],
    )
    assert result.returncode == 0, result.stderr[-2000:]
    record = json.loads((out / "metrics.json").read_text())
    assert record["run"]["model"] == "radarnet_released"
    assert record["protocol"]["preset"] == "radarnet"
    pipeline = ReleasedRadarNet(association, fusion).eval()
    expected = {cap: [] for cap in (50, 70, 80)}
    with torch.no_grad():
        for index, frame in enumerate(frames):
            image = frame_image_as_read(tmp_path / "radarnet", index)
            points = torch.from_numpy(frame["radar"]).float()
            pred = pipeline(image, [points])[0, 0].numpy()
            gt = np.uint32(frame["lidar"] * 256.0) / 256.0
            for cap in expected:
                expected[cap].append(_per_image_mae(pred, gt, cap))
    for cap, maes in expected.items():
        ours = record["test_by_cap"][str(cap)]["mae"]
        assert ours == pytest.approx(float(np.mean(maes)), rel=1e-4)
    report = run_module(
        ["fusion_depth.report", str(out), "--published"], cwd=Path(__file__).parents[1]
    )
    assert report.returncode == 0, report.stderr
    row = next(line for line in report.stdout.splitlines() if line.startswith("| RadarNet"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    mine, published, delta = (float(c) for c in cells[3:6])
    assert mine == pytest.approx(record["test_by_cap"]["80"]["mae"] * 1000, abs=0.05)
    assert published == 2179.3 and delta == pytest.approx(mine - published, abs=0.11)
    assert "(unchecked)" in row


def frame_image_as_read(root: Path, index: int) -> torch.Tensor:
    """Frame ``index``'s JPEG decoded as the reader decodes it, (1, 3, H, W) in [0, 1]."""
    listed = (root / "testing/nuscenes/nuscenes_test_image.txt").read_text().split()[index]
    array = np.asarray(Image.open(root / listed).convert("RGB"))
    return torch.from_numpy(array.copy()).permute(2, 0, 1)[None].float() / 255.0


@pytest.mark.slow
def test_a_foreign_released_file_is_one_line_naming_the_key(tmp_path: Path) -> None:
    """FusionNet's file given as the association network, and a missing one: one line each,
    naming released.<key>, before any frame is read."""
    fusion = write_released(FusionNet(), tmp_path / "model-815000.pth")
    common = [
        "fusion_depth.evaluate",
        "released=radarnet",
        "dataset=radarnet_layout",
        f"dataset.root={tmp_path / 'nothing'}",
        f"paths.cache_dir={tmp_path / 'cache'}",
        f"hydra.run.dir={tmp_path / 'out'}",
    ]
    cases = [
        (
            [f"released.association_weights={fusion}", f"released.fusion_weights={fusion}"],
            f"released.association_weights={fusion}: not RadarNet's released association network",
        ),
        (
            [
                f"released.association_weights={tmp_path / 'gone.pth'}",
                f"released.fusion_weights={fusion}",
            ],
            f"released.association_weights={tmp_path / 'gone.pth'}: no such file",
        ),
    ]
    for extra, expected in cases:
        result = run_module(common + extra, cwd=Path(__file__).parents[1])
        assert result.returncode != 0
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and expected in lines[0], result.stderr[-1500:]
