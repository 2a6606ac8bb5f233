"""The prior computed once per frame (``prior.cache``): keyed by the weights' content, the input
size, the prior's kind and range and each frame's image (a relative prior's normalised, a metric
one's in metres); read back by the training and validation loaders, flipped with the image;
filled ahead by ``prepare``; a missing or damaged file is one line naming it."""

from __future__ import annotations

import json
import os
import shutil

import pytest
import torch
from helpers import run_module
from helpers.prior import offline_environment, refuse_network, tiny_depth_anything

from fusion_depth.data.depth_io import DataFileError
from fusion_depth.data.transforms import TrainAugmentation
from fusion_depth.models.depth_prior import DepthAnythingPrior, normalized_prior
from fusion_depth.runner.prior_cache import CachedPriorFrames, PriorCache, frame_digest


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    refuse_network(monkeypatch)


@pytest.fixture(scope="module")
def tiny_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_depth_anything")
    tiny_depth_anything().save_pretrained(folder)
    return folder


def frames(count=5, seed=0):
    generator = torch.Generator().manual_seed(seed)
    images = torch.randint(0, 256, (count, 3, 32, 48), dtype=torch.uint8, generator=generator)
    return [{"image": image, "index": i} for i, image in enumerate(images)]


def test_filled_once_and_read_back_as_the_prior_computes_it(tmp_path, tiny_folder):
    spec = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    cache = PriorCache(spec, root=tmp_path)
    prior = DepthAnythingPrior(tiny_folder, input_size=28)
    data = frames()
    assert cache.fill(prior, data, "test frames") == 5
    assert cache.fill(prior, data, "test frames") == 0  # all cached
    assert (cache.folder / "meta.json").is_file()
    served = CachedPriorFrames(data, cache)[3]
    expected = normalized_prior(prior(data[3]["image"][None].float() / 255))[0]
    assert served["prior"].dtype == torch.float16 and served["prior"].shape == (1, 32, 48)
    torch.testing.assert_close(served["prior"].float(), expected, rtol=2e-3, atol=1e-3)
    assert served["index"] == 3  # the frame's own keys pass through


class HugePrior(torch.nn.Module):
    """An affine-invariant prior far beyond float16's range, as an SSI-trained network's is."""

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return -5e5 + 1e5 * image[:, :1]


def test_a_prior_beyond_float16_is_stored_by_its_shape(tmp_path, tiny_folder):
    spec = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    cache = PriorCache(spec, root=tmp_path)
    data = frames(2)
    cache.fill(HugePrior(), data, "test frames")
    served = CachedPriorFrames(data, cache)[1]["prior"].float()
    assert torch.isfinite(served).all() and served.min() == 0 and served.max() == 1
    shape = normalized_prior(HugePrior()(data[1]["image"][None].float() / 255))[0]
    torch.testing.assert_close(served, shape, rtol=1e-3, atol=1e-3)


@pytest.fixture(scope="module")
def metric_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_metric")
    tiny_depth_anything(kind="metric", max_depth=80).save_pretrained(folder)
    return folder


def test_a_metric_prior_is_cached_in_metres(tmp_path, metric_folder):
    spec = {"name": "depth_anything_v2", "weights": str(metric_folder), "input_size": 28}
    cache = PriorCache(spec, root=tmp_path)
    assert (cache.kind, cache.max_depth) == ("metric", 80.0)  # read from its config.json
    meta = json.loads((cache.folder / "meta.json").read_text())
    assert (meta["kind"], meta["max_depth"]) == ("metric", 80.0)
    prior = DepthAnythingPrior(metric_folder, input_size=28)
    data = frames(3)
    assert cache.fill(prior, data, "test frames") == 3
    served = CachedPriorFrames(data, cache)[2]["prior"]
    metres = prior(data[2]["image"][None].float() / 255)[0]
    assert served.dtype == torch.float16 and served.shape == (1, 32, 48)
    assert served.max() > 1 and served.max() <= 80  # metres, not normalised to [0, 1]
    torch.testing.assert_close(served.float(), metres, rtol=2**-11, atol=0)


class MetricRamp(torch.nn.Module):
    """A metric prior whose metres are known: 0.5 m to 80 m across the image's first channel."""

    kind, max_depth = "metric", 80.0

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return 0.5 + 79.5 * image[:, :1]


def test_float16_holds_metres_to_a_relative_2e_minus_11(tmp_path, metric_folder):
    spec = {"name": "depth_anything_v2", "weights": str(metric_folder), "input_size": 28}
    cache = PriorCache(spec, root=tmp_path)
    data = frames(2)
    cache.fill(MetricRamp(), data, "test frames")
    served = CachedPriorFrames(data, cache)[1]["prior"].float()
    exact = MetricRamp()(data[1]["image"][None].float() / 255)[0]
    error = (served - exact).abs()
    assert (error <= exact * 2**-11).all()  # half of float16's step: 3 cm at most, near 80 m
    assert error.max() <= 0.0625 / 2 and exact.max() > 64


def test_relative_and_metric_caches_never_mix(tmp_path, tiny_folder, metric_folder):
    from fusion_depth.errors import ArgumentError

    # A .pth whose name says neither kind is read as either: two caches of one file.
    pth = tmp_path / "weights.pth"
    torch.save({"pretrained.cls_token": torch.zeros(1)}, pth)  # only its bytes are hashed here
    relative = {"name": "depth_anything_v2", "weights": str(pth), "input_size": 28}
    metric = {**relative, "kind": "metric", "max_depth": 80}
    folder = PriorCache(relative, root=tmp_path).folder
    assert PriorCache({**relative, "kind": "relative"}, root=tmp_path).folder == folder
    assert PriorCache(metric, root=tmp_path).folder != folder
    ranges = {PriorCache({**metric, "max_depth": m}, root=tmp_path).folder for m in (20, 80)}
    assert len(ranges) == 2
    # A folder's kind comes from its config.json: null and its own kind are one cache.
    spec = {"name": "depth_anything_v2", "weights": str(metric_folder), "input_size": 28}
    same = PriorCache({**spec, "kind": "metric", "max_depth": 80}, root=tmp_path).folder
    assert same == PriorCache(spec, root=tmp_path).folder
    with pytest.raises(ArgumentError, match=r"^kind=relative: .*config.json sets"):
        PriorCache({**spec, "kind": "relative"}, root=tmp_path)
    # A prior of another kind cannot fill a cache: its frames would be read in another form.
    cache = PriorCache(spec, root=tmp_path)
    relative_prior = DepthAnythingPrior(tiny_folder, input_size=28)
    with pytest.raises(ArgumentError, match=r"^kind=metric: the prior cache .* kind=relative"):
        cache.fill(relative_prior, frames(1), "test frames")
    assert not list(cache.folder.glob("*/*.npy"))


def test_other_weights_input_size_or_image_find_no_stale_prior(tmp_path, tiny_folder):
    spec = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    folder = PriorCache(spec, root=tmp_path).folder
    assert PriorCache({**spec, "input_size": 42}, root=tmp_path).folder != folder
    edited = tmp_path / "edited"
    shutil.copytree(tiny_folder, edited)
    same = PriorCache({**spec, "weights": str(edited)}, root=tmp_path).folder
    assert same == folder  # the same bytes elsewhere: the same cache
    with (edited / "config.json").open("a") as f:
        f.write(" ")  # one byte more in the same file at the same path
    assert PriorCache({**spec, "weights": str(edited)}, root=tmp_path).folder != folder
    image = frames(1)[0]["image"]
    changed = image.clone()
    changed[0, 0, 0] ^= 1
    assert frame_digest(changed) != frame_digest(image)
    assert frame_digest(image.float()) != frame_digest(image)


def test_a_missing_or_damaged_cached_prior_is_one_line_naming_it(tmp_path, tiny_folder):
    spec = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    cache = PriorCache(spec, root=tmp_path)
    data = frames(2)
    with pytest.raises(DataFileError, match=r"no cached prior for this frame; run python -m"):
        CachedPriorFrames(data, cache)[0]
    cache.fill(DepthAnythingPrior(tiny_folder, input_size=28), data, "test frames")
    path = cache.path(frame_digest(data[1]["image"]))
    path.write_bytes(path.read_bytes()[:100])  # truncated
    with pytest.raises(DataFileError, match=rf"^{path}"):
        CachedPriorFrames(data, cache)[1]
    CachedPriorFrames(data, cache)[0]  # the other frame still reads


def dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    import subprocess
    import sys

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_a_rerun_removes_the_temporaries_of_a_killed_fill(tmp_path, tiny_folder):
    """A kill while the cache fills leaves ``.<digest>.npy.p<pid>h<host>.<random>.npy``; the
    next run that opens the cache removes those of gone processes, never a live writer's."""
    from fusion_depth.utils.atomic import host_tag

    spec = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    data = frames(2)
    cache = PriorCache(spec, root=tmp_path)
    cache.fill(DepthAnythingPrior(tiny_folder, input_size=28), data, "test frames")
    final = cache.path(frame_digest(data[0]["image"]))
    shard = final.parent
    orphan = shard / f".{'ab' * 32}.npy.p{dead_pid()}h{host_tag()}.x1y2z3.npy"
    live = shard / f".{'cd' * 32}.npy.p{os.getpid()}h{host_tag()}.q4r5s6.npy"
    for path in (orphan, live):
        path.write_bytes(b"half a prior")
    again = PriorCache(spec, root=tmp_path)  # the rerun opens the same folder
    assert again.folder == cache.folder
    assert not orphan.exists()
    assert live.exists()  # a process that is alive may be writing it
    assert final.is_file()  # finished frames stay
    assert again.fill(DepthAnythingPrior(tiny_folder, input_size=28), data, "test frames") == 0
    assert sorted(p.name for p in shard.iterdir() if p.name.startswith(".")) == [live.name]


def test_the_flip_moves_the_cached_prior_with_the_image():
    image = torch.rand(2, 3, 8, 12)
    batch = {
        "image": image,
        "sparse": torch.rand(2, 1, 8, 12),
        "depth": torch.rand(2, 1, 8, 12),
        "prior": image[:, :1].half(),  # the prior lines up with the image's first channel
    }
    out = TrainAugmentation(flip_p=1.0, color_p=0.0)(batch)
    torch.testing.assert_close(out["prior"], image[:, :1].flip(-1).half().float())
    torch.testing.assert_close(out["image"], image.flip(-1))


@pytest.mark.slow
def test_prepare_fills_it_and_training_reads_it(tmp_path, tiny_folder):
    prior = ["prior=depth_anything_v2", f"prior.weights={tiny_folder}", "prior.input_size=28"]
    environment = {**offline_environment(), "FUSION_DEPTH_CACHE": str(tmp_path / "cache")}
    prepared = run_module(
        ["fusion_depth.prepare", "experiment=smoke", *prior, f"hydra.run.dir={tmp_path}/p"],
        cwd=tmp_path,
        env=environment,
    )
    assert prepared.returncode == 0, prepared.stderr[-2000:]
    assert "prior=depth_anything_v2: 12 frames computed" in prepared.stdout  # 8 train + 4 val
    (folder,) = (tmp_path / "cache" / "priors").iterdir()
    assert len(list(folder.glob("*/*.npy"))) == 12
    trained = run_module(
        [
            "fusion_depth.train",
            "experiment=smoke",
            "logger=none",
            *prior,
            f"hydra.run.dir={tmp_path}/t",
        ],
        cwd=tmp_path,
        env=environment,
    )
    assert trained.returncode == 0, trained.stderr[-2000:]
    assert "frames of the train split computed" not in trained.stderr  # read, not computed
    # Training serves the cache: a damaged file stops the next run, naming it.
    victim = sorted(folder.glob("*/*.npy"))[0]
    victim.write_bytes(b"not an array")
    broken = run_module(
        [
            "fusion_depth.train",
            "experiment=smoke",
            "logger=none",
            *prior,
            f"hydra.run.dir={tmp_path}/b",
        ],
        cwd=tmp_path,
        env=environment,
    )
    assert broken.returncode == 1
    assert str(victim) in broken.stderr and "Traceback" not in broken.stderr
    on_the_fly = run_module(
        [
            "fusion_depth.train",
            "experiment=smoke",
            "logger=none",
            *prior,
            "prior.cache=false",
            f"hydra.run.dir={tmp_path}/f",
        ],
        cwd=tmp_path,
        env=environment,
    )
    assert on_the_fly.returncode == 0, on_the_fly.stderr[-2000:]


@pytest.mark.slow
def test_bench_reads_the_prior_and_the_network_on_top_apart(tmp_path, tiny_folder):
    result = tmp_path / "bench.json"
    prior = ["prior=depth_anything_v2", f"prior.weights={tiny_folder}", "prior.input_size=28"]
    timed = run_module(
        ["fusion_depth.bench", "--only", "infer", "--runs", "2", "--json", str(result)]
        + ["experiment=smoke", *prior],
        cwd=tmp_path,
        env=offline_environment(),
    )
    assert timed.returncode == 0, timed.stderr[-2000:]
    infer = json.loads(result.read_text())["infer"]
    assert infer["prior_latency_s_median"] > 0 and infer["head_latency_s_median"] > 0
    assert "the prior alone" in timed.stdout and "the network on top of it" in timed.stdout
