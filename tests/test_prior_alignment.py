"""A prior's global alignment scored with no training (``evaluate prior=...``), and a
checkpoint's prior read from another file (``evaluate ckpt_path=... prior.weights=...``)."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from helpers import run_module
from helpers.prior import KnownPrior, offline_environment, refuse_network, tiny_depth_anything

from fusion_depth.errors import ArgumentError
from fusion_depth.models.prior_alignment import GlobalAlignment
from fusion_depth.report import main as report_main


@pytest.fixture(autouse=True)
def no_network(monkeypatch):
    refuse_network(monkeypatch)


@pytest.fixture(scope="module")
def tiny_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_depth_anything")
    tiny_depth_anything().save_pretrained(folder)
    return folder


def test_a_perfect_prior_aligns_to_the_true_depth_and_frames_without_returns_fall_back(
    tiny_folder,
):
    torch.manual_seed(0)
    depth = 2.0 + 40.0 * torch.rand(3, 1, 32, 48)
    sparse = torch.where(torch.rand_like(depth) < 0.05, depth, 0.0)
    sparse[1] = 0  # no return: the batch's median fit
    prior = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    net = GlobalAlignment(prior, min_depth=0.5, max_depth=80.0).eval()
    net.prior = KnownPrior(depth)
    out = net(torch.rand(3, 3, 32, 48), sparse)
    torch.testing.assert_close(out, depth, rtol=1e-5, atol=0)  # frame 1 too: same affine map
    assert net.fit_summary() == {
        "kind": "relative",
        "ransac_iterations": 100,  # RANSAC by default
        "fits": 3,
        "fallbacks": 1,
        "reversed": 0,  # frame 1 had no returns: too few, not reversed
    }
    # A batch with no return at all takes the mean of the batches' fits so far: 3 and 0.25.
    torch.testing.assert_close(net.fit_mean, torch.tensor([1 / 3, -0.25 / 3], dtype=torch.float64))
    alone = net(torch.rand(3, 3, 32, 48), torch.zeros_like(sparse))
    torch.testing.assert_close(alone, depth, rtol=1e-5, atol=0)
    assert net.fit_summary()["fallbacks"] == 4


def test_alignment_settings_are_checked_when_built(tiny_folder):
    prior = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    with pytest.raises(ArgumentError, match=r"^ransac_threshold=-0.1: expected a relative"):
        GlobalAlignment(prior, ransac_threshold=-0.1)
    with pytest.raises(ArgumentError, match=r"^ransac_iterations=1.5: expected an integer ≥ 0"):
        GlobalAlignment(prior, ransac_iterations=1.5)
    with pytest.raises(ArgumentError, match=r"^name=none: the global alignment needs a prior"):
        GlobalAlignment({"name": "none"})


def _evaluate(cwd, *overrides):
    return run_module(["fusion_depth.evaluate", *overrides], cwd=cwd, env=offline_environment())


@pytest.mark.slow
def test_evaluate_scores_the_alignment_and_sweeps_its_settings(tmp_path, tiny_folder, capsys):
    prior = ["prior=depth_anything_v2", f"prior.weights={tiny_folder}", "prior.input_size=28"]
    sweep = _evaluate(
        tmp_path,
        "-m",
        "experiment=smoke",
        "dataset=procedural",
        *prior,
        "alignment.ransac_iterations=0,100",
        f"hydra.sweep.dir={tmp_path}/sweep",
    )
    assert sweep.returncode == 0, sweep.stderr[-2000:]
    assert "2 ok" in sweep.stdout + sweep.stderr  # the sweep's summary counts both
    written = sorted((tmp_path / "sweep").glob("*/metrics.json"))
    records = [json.loads(path.read_text()) for path in written]
    records.sort(key=lambda record: record["alignment"]["ransac_iterations"])
    assert [r["alignment"]["ransac_iterations"] for r in records] == [0, 100]
    for record in records:
        assert record["run"]["model"] == "prior_alignment"
        assert record["run"]["backbone"] == "depth_anything_v2"
        assert record["alignment"]["fits"] == record["test"]["num_images"] > 0
        assert 0 <= record["alignment"]["fallbacks"] < record["alignment"]["fits"]
        assert 0 <= record["alignment"]["reversed"] <= record["alignment"]["fallbacks"]
        assert record["alignment"]["kind"] == "relative"
        assert 0 < record["test"]["rmse"] < 80
    assert records[0]["test"]["rmse"] != records[1]["test"]["rmse"]
    # Each fit is its own row in report: its settings are the record's overrides.
    assert "alignment.ransac_iterations=0" in records[0]["run"]["overrides"]
    assert "alignment.ransac_iterations=100" in records[1]["run"]["overrides"]
    # report tabulates them: one row per fit, named by its settings, no training time ("–", the
    # last column) and no training loss (one value in every row: "none", under the table).
    assert report_main([str(tmp_path / "sweep"), "--time"]) == 0
    # (its settings shortened: ransac_iterations=0; what both share is named under the table)
    out = capsys.readouterr().out
    rows = [
        line for line in out.splitlines() if line.startswith("|") and " ransac_iterations=" in line
    ]
    assert len(rows) == 2 and all(row.rstrip(" |").endswith("–") for row in rows), rows
    assert "Loss none" in out
    ceiling = _evaluate(
        tmp_path, "experiment=smoke", "dataset=procedural", *prior,
        "alignment.target=ground_truth", f"hydra.run.dir={tmp_path}/gt",
    )  # fmt: skip
    assert ceiling.returncode == 0, ceiling.stderr[-2000:]
    record = json.loads((tmp_path / "gt" / "metrics.json").read_text())
    assert record["alignment"]["target"] == "ground_truth"
    assert record["alignment"]["fits"] == record["test"]["num_images"]
    assert "alignment.target=ground_truth" in record["run"]["overrides"]
    assert records[0]["alignment"]["target"] == "sparse"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["dataset=procedural", "prior.weights=/no/such"], "prior.weights=/no/such: no such file"),
        (
            ["dataset=procedural", "prior.weights={tiny}", "alignment.ransac_threshold=0"],
            "alignment.ransac_threshold=0: expected a relative error > 0",
        ),
        (["prior.weights={tiny}"], "choose the dataset to fit and score it on with dataset="),
    ],
)
@pytest.mark.slow
def test_bad_alignment_settings_fail_in_one_line(tmp_path, tiny_folder, overrides, message):
    overrides = [o.replace("{tiny}", str(tiny_folder)) for o in overrides]
    failed = _evaluate(
        tmp_path, "prior=depth_anything_v2", *overrides, f"hydra.run.dir={tmp_path}/e"
    )
    assert failed.returncode == 1
    assert message in failed.stderr
    assert "Traceback" not in failed.stderr
    assert not (tmp_path / "e" / "metrics.json").exists()


@pytest.mark.slow
def test_a_checkpoint_reads_its_prior_from_another_file(tmp_path, tiny_folder):
    moved = tmp_path / "moved"
    shutil.copytree(tiny_folder, moved)
    run = tmp_path / "run"
    trained = run_module(
        [
            "fusion_depth.train",
            "experiment=smoke",
            "logger=none",
            "prior=depth_anything_v2",
            f"prior.weights={moved}",
            "prior.input_size=28",
            f"hydra.run.dir={run}",
        ],
        cwd=tmp_path,
        env=offline_environment(),
    )
    assert trained.returncode == 0, trained.stderr[-2000:]
    (checkpoint,) = (run / "checkpoints").glob("epoch*.ckpt")
    shutil.move(moved, tmp_path / "elsewhere")  # the file the checkpoint names is gone
    gone = _evaluate(tmp_path, f"ckpt_path={checkpoint}", f"hydra.run.dir={tmp_path}/gone")
    assert gone.returncode == 1 and "no such file" in gone.stderr
    assert "Traceback" not in gone.stderr
    prior = ["prior=depth_anything_v2", f"prior.weights={tmp_path / 'elsewhere'}"]
    found = _evaluate(tmp_path, f"ckpt_path={checkpoint}", *prior, f"hydra.run.dir={tmp_path}/e")
    assert found.returncode == 0, found.stderr[-2000:]
    rescored = json.loads((tmp_path / "e" / "metrics.json").read_text())
    tested = json.loads((run / "metrics.json").read_text())
    assert rescored["test"]["rmse"] == pytest.approx(tested["test"]["rmse"], rel=1e-4)
    # Served without its prior (as prior.dropout trained it to take): no prior file is read.
    without = _evaluate(
        tmp_path, f"ckpt_path={checkpoint}", "prior=none", f"hydra.run.dir={tmp_path}/n"
    )
    assert without.returncode == 0, without.stderr[-2000:]
    record = json.loads((tmp_path / "n" / "metrics.json").read_text())
    assert "prior=none" in record["run"]["overrides"]  # report keeps it apart from the run
    assert not moved.exists()  # the file the checkpoint names is gone, and was not needed
    predicted = run_module(
        [
            "fusion_depth.predict",
            f"ckpt_path={checkpoint}",
            "prior=none",
            "input=split:test",
            "limit=2",
            f"hydra.run.dir={tmp_path}/p",
        ],
        cwd=tmp_path,
        env=offline_environment(),
    )
    assert predicted.returncode == 0, predicted.stderr[-2000:]
    assert len(list((tmp_path / "p" / "predictions").glob("*.png"))) >= 2
    other = _evaluate(
        tmp_path,
        f"ckpt_path={checkpoint}",
        "prior=checkpoint",
        f"prior.weights={checkpoint}",
        f"hydra.run.dir={tmp_path}/o",
    )
    assert other.returncode == 1
    assert "prior=checkpoint: ckpt_path=" in other.stderr
    assert "was trained with prior=depth_anything_v2" in other.stderr


def test_a_network_trained_with_a_prior_serves_without_it(tiny_folder):
    from fusion_depth.models import DepthNet, create_model

    spec = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    torch.manual_seed(0)
    trained = DepthNet("resnet10t", "concat", prior=spec).eval()
    served = DepthNet("resnet10t", "concat", prior={**spec, "enabled": False}).eval()
    assert served.prior is None  # not built: no weights file is read
    served.load_state_dict(trained.state_dict())
    image, sparse = torch.rand(2, 3, 64, 96), torch.rand(2, 1, 64, 96) * 40
    trained.prior_input = lambda image, cached=None: torch.zeros_like(image[:, :1])
    torch.testing.assert_close(served(image, sparse), trained(image, sparse))
    with pytest.raises(ArgumentError, match=r"^prior=none: model=prior_correction corrects"):
        create_model("prior_correction", prior={**spec, "enabled": False})


def test_the_ceiling_fits_each_frame_to_its_ground_truth():
    from fusion_depth.evaluate.scoring import GroundTruthAsSparse

    class Split(torch.utils.data.Dataset):
        def __len__(self):
            return 1

        def __getitem__(self, index):
            return {
                "image": torch.zeros(3, 2, 2),
                "sparse": torch.zeros(1, 2, 2),
                "depth": torch.ones(1, 2, 2),
            }

        def encoded_sample(self, index):
            return {**self[index], "depth": torch.full((1, 2, 2), 256, dtype=torch.uint16)}

    swapped = GroundTruthAsSparse(Split())
    assert swapped[0]["sparse"].tolist() == swapped[0]["depth"].tolist()
    encoded = swapped.encoded_sample(0)
    assert encoded["sparse"].dtype == torch.uint16 and int(encoded["sparse"][0, 0, 0]) == 256


class KnownMetricPrior(torch.nn.Module):
    """A metric prior off by a scale (a camera other than its training one)."""

    kind = "metric"

    def __init__(self, depth: torch.Tensor) -> None:
        super().__init__()
        self.depth = depth

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.depth / 1.25


def test_a_metric_prior_is_aligned_by_a_scale_alone(tiny_folder):
    torch.manual_seed(0)
    depth = 2.0 + 40.0 * torch.rand(2, 1, 32, 48)
    sparse = torch.where(torch.rand_like(depth) < 0.05, depth, 0.0)
    prior = {"name": "depth_anything_v2", "weights": str(tiny_folder), "input_size": 28}
    net = GlobalAlignment(prior, min_depth=0.5, max_depth=80.0).eval()
    net.prior, net.kind = KnownMetricPrior(depth), "metric"
    out = net(torch.rand(2, 3, 32, 48), sparse)
    torch.testing.assert_close(out, depth, rtol=1e-5, atol=0)
    assert net.fit_summary()["kind"] == "metric"
    torch.testing.assert_close(net.fit_mean, torch.tensor([1.25, 0.0], dtype=torch.float64))


def test_a_metric_folder_makes_a_metric_alignment(tmp_path):
    folder = tmp_path / "metric"
    tiny_depth_anything(kind="metric", max_depth=80).save_pretrained(folder)
    prior = {"name": "depth_anything_v2", "weights": str(folder), "input_size": 28}
    net = GlobalAlignment(prior, min_depth=0.5, max_depth=80.0)
    assert net.kind == "metric" and net.prior.kind == "metric"


@pytest.mark.slow
def test_the_oracle_prior_aligns_within_two_metres_under_ransac(tmp_path):
    """The global alignment of a perfect prior (``3 / depth + 0.2``, the frame's own ground
    truth) to the built-in radar: RANSAC over returns recovers it, plain least squares is
    pulled off by the radar's outliers. (On the 250 test frames of the built-in dataset:
    1.01 m and 4.88 m, docs/results/prior.md.)"""
    sweep = _evaluate(
        tmp_path,
        "-m",
        "prior=oracle",
        "dataset=procedural",
        "dataset.num_test=25",
        "alignment.ransac_iterations=0,100",
        f"hydra.sweep.dir={tmp_path}/sweep",
    )
    assert sweep.returncode == 0, sweep.stderr[-2000:]
    records = [json.loads(p.read_text()) for p in (tmp_path / "sweep").glob("*/metrics.json")]
    by_fit = {r["alignment"]["ransac_iterations"]: r for r in records}
    assert by_fit[100]["test"]["rmse"] < 2.0 < by_fit[0]["test"]["rmse"]
    assert by_fit[100]["alignment"]["fallbacks"] == 0
    assert by_fit[100]["checkpoint"] == "prior=oracle"  # read from no file
    both = _evaluate(
        tmp_path, "prior=oracle", "dataset=procedural", "alignment.target=ground_truth",
        f"hydra.run.dir={tmp_path}/both",
    )  # fmt: skip
    assert both.returncode == 1 and "fits the ground truth to itself" in both.stderr


def test_the_oracle_prior_cannot_run_on_an_image():
    from fusion_depth.models.depth_prior import build_prior, oracle_prior

    with pytest.raises(ValueError, match=r"^prior=oracle is each frame's ground truth"):
        build_prior("oracle")(torch.rand(1, 3, 8, 8))
    depth = torch.tensor([[[[0.0, 3.0, 30.0]]]])
    torch.testing.assert_close(oracle_prior(depth), torch.tensor([[[[0.2, 1.2, 0.3]]]]))
