"""RadarCam-Depth's Scale Map Learner (:mod:`fusion_depth.models.scale_map_learner`) against its
authors' own code, on fixtures that code made (``tests/fixtures/scale_map_learner_authors``,
written by ``scripts/make_scale_map_learner_parity_fixtures.py`` from MMOCKING/RadarCam-Depth
at the commit the fixtures record): the network's weights load strictly from a file in their
layout, its raw output, prediction and final depth equal theirs within 1e-5 relative (fp32,
CPU) in eval mode on a frame their ``validate`` ran and in train mode on their training step,
the scaffold and the network's inputs built here are theirs bit for bit, the losses and the
global alignment are theirs, the shipped checkpoint layout loads strictly, and a file with a
renamed, missing or reshaped key, or no checkpoint at all, fails in one line naming it.

The fixtures hold no weights (the shipped network has 21 M values): the script's
``fixture_weights`` makes them from the recorded layout, checked against the recorded
SHA-256."""

from __future__ import annotations

import argparse
import contextlib
import copy
import functools
import importlib.util
import json
import random
from collections import OrderedDict

import pytest
import torch
from helpers import REPO

from fusion_depth.errors import ArgumentError, ArgumentFileError
from fusion_depth.models.scale_map_learner import (
    AUTHORS_COMMIT,
    EPOCHS,
    LEARNING_RATES,
    MAX_PRED_DEPTH_TEST,
    MAX_PRED_DEPTH_TRAIN,
    MIN_PRED_DEPTH,
    SKY_DEPTH,
    ZJU_ROWS,
    ReleasedWeightsError,
    ScaleMapLearner,
    global_alignment,
    learning_rate,
    load_released,
    network_size,
    released_depth,
    resize_nearest,
    scale_scaffold,
    sml_inputs,
    sml_loss,
    sml_prediction,
    sobel_filter,
)

FIXTURES = REPO / "tests" / "fixtures" / "scale_map_learner_authors"
SCRIPT = REPO / "scripts" / "make_scale_map_learner_parity_fixtures.py"
RTOL = 1e-5  # relative, no absolute slack: fp32 on a CPU, at the fixtures' thread count
LOSS_RTOL = 1e-6
# At another thread count the convolutions round otherwise: measured at one thread against the
# fixtures' two, on the same 2-core Xeon, 8.9e-6 of the raw output.
OTHER_THREADS_OUT_ATOL = 1e-4
# Their global alignment sums in numpy float32, ours in float64: their fit's shift is 1.3e-5 m
# off the float64 one on the "fit" frame (-0.135795 against -0.135782 m; ours is their formula in
# float64 bit for bit), which is every pixel's difference. Their PNG keeps 1/256 m.
ALIGNMENT_ATOL = 1e-4  # metres


@functools.cache
def _script():
    """The fixtures' script, for its fixture_weights and weights_digest."""
    spec = importlib.util.spec_from_file_location("make_sml_fixtures", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def _threads(count: int):
    """Run with ``count`` threads: how convolutions split their sums decides their rounding,
    so the fixtures compare bitwise only at the thread count that made them."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _metres(codes: torch.Tensor) -> torch.Tensor:
    """A PNG's codes as their ``load_sparse_depth`` reads them (/ 256, float32), (1, 1, H, W)."""
    return (codes.to(torch.float32) / 256.0)[None, None]


@pytest.fixture(scope="module")
def record() -> dict:
    return json.loads((FIXTURES / "fixtures.json").read_text())


@pytest.fixture(scope="module")
def shipped() -> dict:
    return json.loads((FIXTURES / "shipped_layout.json").read_text())


@pytest.fixture(scope="module")
def layout(shipped) -> dict:
    return shipped["checkpoint"]["network"]


@pytest.fixture(scope="module")
def cases() -> dict:
    return torch.load(FIXTURES / "cases.pt", weights_only=True)


@pytest.fixture(scope="module")
def net(record, layout, tmp_path_factory) -> ScaleMapLearner:
    """Ours, with the fixtures' weights loaded from a file as their ``BaseModel.save`` writes
    it (a flat state dict), named as their training names it."""
    weights = _script().fixture_weights(layout)
    assert _script().weights_digest(weights) == record["weights_sha256"]
    path = tmp_path_factory.mktemp("released") / "model-6000.pth"
    torch.save(OrderedDict(weights), path)
    del weights
    model = ScaleMapLearner()
    assert load_released(model, path) == 6000
    path.unlink()
    return model.eval()


@pytest.fixture(scope="module")
def fresh_net() -> ScaleMapLearner:
    """Ours with storage, for files that must load (each test overwrites its values)."""
    return ScaleMapLearner()


@pytest.fixture(scope="module")
def meta_net() -> ScaleMapLearner:
    """Ours without storage: enough to check a file's keys and shapes."""
    with torch.device("meta"):
        return ScaleMapLearner()


def _test_inputs(cases: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """Frame ``test``'s RC-Net depth and ``mono_ga`` (cropped to ZJU's rows as their dataset
    crops it), metres."""
    case = cases["test"]
    top, bottom = ZJU_ROWS
    return _metres(case["rcnet_png"]), _metres(case["mono_ga_png"][top:bottom])


def _train_inputs(cases: dict) -> tuple[torch.Tensor, torch.Tensor]:
    case = cases["train"]
    return _metres(case["rcnet_png"]), _metres(case["mono_ga_png"])


def test_the_fixtures_and_their_script_name_the_authors_commit(record, shipped) -> None:
    assert record["authors_commit"] == shipped["authors_commit"] == AUTHORS_COMMIT
    assert AUTHORS_COMMIT in SCRIPT.read_text()
    assert {call["model"] for call in record["hub_calls"]} == {"tf_efficientnet_lite3"}
    assert all(call["exportable"] for call in record["hub_calls"])
    size = sum(path.stat().st_size for path in FIXTURES.iterdir())
    assert size < 2_000_000, f"the fixtures take {size} bytes"


def test_the_scaffold_is_theirs_bit_for_bit(cases) -> None:
    """From RC-Net's depth and ``mono_ga``: 1.0 where no point (0 m, and the 85 m band past
    80 m), the scale elsewhere, min-max normalised over the frame."""
    rcnet, mono_ga = _test_inputs(cases)
    scaffold = scale_scaffold(rcnet, mono_ga)
    assert torch.equal(scaffold[0, 0], cases["test"]["scaffold"])
    assert bool((rcnet >= 80).any()) and bool(((rcnet > 0) & (rcnet < 80)).any())


@pytest.mark.parametrize("frame", ["test", "train"])
def test_the_network_inputs_are_theirs_bit_for_bit(cases, frame) -> None:
    """``x`` (normalised inverse depth and scaffold) and ``d`` at the network's size: 288×64
    from ZJU's 300×64 crop, 64×288 from 40×144 (2.5 × 32 rounds to 2 × 32)."""
    rcnet, mono_ga = (_test_inputs if frame == "test" else _train_inputs)(cases)
    x, d = sml_inputs(rcnet, mono_ga)
    assert tuple(x.shape[-2:]) == {"test": (288, 64), "train": (64, 288)}[frame]
    assert torch.equal(x, cases[frame]["x"])
    assert torch.equal(d, cases[frame]["d"])


def test_the_output_equals_theirs_in_eval_mode(net, record, cases) -> None:
    """Frame ``test`` as ``sml_run_zju.py`` runs it: raw output, then ``pred`` with
    ``min_pred`` 0.1 and ``max_pred`` 100, both bounds reached."""
    case = cases["test"]
    with _threads(record["threads"]), torch.no_grad():
        out = net(case["x"])
    torch.testing.assert_close(out, case["out"], rtol=RTOL, atol=0)
    pred, scales = sml_prediction(out, case["d"], MIN_PRED_DEPTH, MAX_PRED_DEPTH_TEST)
    torch.testing.assert_close(pred, case["pred"], rtol=RTOL, atol=0)
    assert bool((scales == 0).any()), "1 + out < 0 somewhere: the ReLU acts"
    assert bool((case["pred"] == torch.tensor(1 / MAX_PRED_DEPTH_TEST)).any())
    assert bool((case["pred"] == torch.tensor(1 / MIN_PRED_DEPTH)).any())


def test_the_output_equals_theirs_in_train_mode(net, record, cases) -> None:
    """Their training step's forward (batch statistics in every batch norm), ``max_pred``
    255."""
    case = cases["train"]
    training = copy.deepcopy(net).train()
    with _threads(record["threads"]), torch.no_grad():
        out = training(case["x"])
    torch.testing.assert_close(out, case["out"], rtol=RTOL, atol=0)
    pred, _ = sml_prediction(out, case["d"], MIN_PRED_DEPTH, MAX_PRED_DEPTH_TRAIN)
    torch.testing.assert_close(pred, case["pred"], rtol=RTOL, atol=0)
    with _threads(record["threads"]), torch.no_grad():
        assert not torch.allclose(net(case["x"]), case["out"], rtol=100 * RTOL, atol=0)


def test_the_final_depth_equals_what_they_save(net, record, cases) -> None:
    """End to end from the two depth maps: their ``validate``'s bicubic resize to the input's
    300×64, with ``mono_ga`` kept where it is 200 m or more (their saved PNGs)."""
    rcnet, mono_ga = _test_inputs(cases)
    with _threads(record["threads"]):
        depth = released_depth(net, rcnet, mono_ga, sky_depth=SKY_DEPTH)
    theirs = cases["test"]["depth"]
    torch.testing.assert_close(depth[0, 0], theirs, rtol=RTOL, atol=0)
    assert bool((mono_ga >= SKY_DEPTH).any()) and bool((mono_ga < SKY_DEPTH).any())


def test_at_one_thread_the_output_moves_by_float_rounding_only(net, cases) -> None:
    with _threads(1), torch.no_grad():
        out = net(cases["test"]["x"])
    torch.testing.assert_close(out, cases["test"]["out"], rtol=0, atol=OTHER_THREADS_OUT_ATOL)


def test_the_comparison_has_power(net, record, cases) -> None:
    """The raw output depends on the scaffold channel and the scaffold on its fill value: a
    scaffold of zeros, or a fill of 0 where no point, moves it far past the tolerance."""
    case = cases["test"]
    x = case["x"].clone()
    x[:, 1] = 0
    with _threads(record["threads"]), torch.no_grad():
        assert not torch.allclose(net(x), case["out"], rtol=100 * RTOL, atol=0)
    rcnet, mono_ga = _test_inputs(cases)
    valid = (rcnet > 0) & (rcnet < 80)
    scales = torch.where(valid, mono_ga / rcnet, torch.zeros_like(rcnet))
    zero_fill = (scales - scales.min()) / (scales.max() - scales.min())
    assert not torch.allclose(zero_fill, scale_scaffold(rcnet, mono_ga), atol=0.01)


def test_the_targets_are_resized_as_theirs(cases) -> None:
    """``gt`` and ``sparse_gt`` as their training step handed them to ``compute_loss``."""
    case = cases["train"]
    size = tuple(case["x"].shape[-2:])
    assert torch.equal(resize_nearest(_metres(case["gt_png"]), size), case["gt"])
    assert torch.equal(resize_nearest(_metres(case["sparse_gt_png"]), size), case["sparse_gt"])


def test_the_training_loss_equals_theirs(cases) -> None:
    """Their step's loss (smooth L1, lidar weight 3) on their prediction and targets."""
    case = cases["train"]
    loss, info = sml_loss(1.0 / case["pred"], case["gt"], case["sparse_gt"])
    torch.testing.assert_close(loss, case["loss"], rtol=LOSS_RTOL, atol=0)
    for key in ("loss_supervised", "loss_lidar"):
        torch.testing.assert_close(info[key], case[key], rtol=LOSS_RTOL, atol=0)
    assert bool(((case["gt"] > 0) & (case["sparse_gt"] > 0)).any()), "the lidar mask acts"


def test_the_other_loss_settings_equal_theirs(record, cases) -> None:
    """Their ``compute_loss`` with l1, l2, no lidar term, the gradient smoothness and the 7×7
    Sobel smoothness (edges from the aligned depth ``1 / d``)."""
    case = cases["train"]
    output, image = 1.0 / case["pred"], 1.0 / case["d"]
    for name, value in record["losses"].items():
        func, w_smoothness, kernel, w_lidar = value["settings"]
        loss, info = sml_loss(
            output, case["gt"], case["sparse_gt"], image, func, w_lidar, w_smoothness, kernel
        )
        for key in ("loss", "loss_supervised", "loss_smoothness", "loss_lidar"):
            assert float(info[key]) == pytest.approx(value[key], rel=LOSS_RTOL, abs=0), (name, key)
        assert float(loss) == pytest.approx(value["loss"], rel=LOSS_RTOL, abs=0)


@pytest.mark.parametrize("frame", ["fit", "singular"])
def test_the_global_alignment_equals_theirs(cases, frame) -> None:
    """Their ``process_scale``: least squares on depth over the radar pixels in (2, 80) m,
    floored at 1/255 m; a single point is singular (scale and shift 0)."""
    case = cases["alignment"][frame]
    aligned = global_alignment(_metres(case["mono_png"]), _metres(case["radar_png"]))
    torch.testing.assert_close(aligned[0, 0], case["aligned"], rtol=0, atol=ALIGNMENT_ATOL)
    if frame == "singular":
        assert bool((case["aligned"] == torch.tensor(1 / 255.0)).all())


def test_the_network_size_is_their_transforms() -> None:
    """The side whose scale to 288 is nearer 1 goes to 288, the other by the same factor,
    rounded half to even to a multiple of 32."""
    assert network_size(300, 1280) == (288, 1216)  # ZJU's crop
    assert network_size(40, 144) == (64, 288)  # 2.5 → 2
    assert network_size(300, 64) == (288, 64)
    assert network_size(900, 1600) == (288, 512)
    with pytest.raises(ArgumentError, match=r"^size=10x1000: .* 0x288$"):
        network_size(10, 1000)


def test_nearest_resizing_is_opencvs() -> None:
    cv2 = pytest.importorskip("cv2")
    rng = random.Random(0)
    for _ in range(200):
        source = (rng.randint(1, 400), rng.randint(1, 700))
        target = (rng.randint(1, 400), rng.randint(1, 700))
        x = torch.arange(source[0] * source[1], dtype=torch.float32).reshape(source)
        theirs = cv2.resize(x.numpy(), target[::-1], interpolation=cv2.INTER_NEAREST)
        assert torch.equal(resize_nearest(x, target), torch.from_numpy(theirs)), (source, target)


def test_the_prediction_scales_and_clamps_inverse_depth() -> None:
    out = torch.tensor([-2.0, -0.5, 0.0, 3.0, 9.0]).reshape(1, 1, 1, 5)
    d = torch.tensor([0.5, 0.5, 0.005, 0.5, 2.0]).reshape(1, 1, 1, 5)
    pred, scales = sml_prediction(out, d, min_pred=0.1, max_pred=100.0)
    assert scales.flatten().tolist() == [0.0, 0.5, 1.0, 4.0, 10.0]
    assert pred.flatten().tolist() == pytest.approx([0.01, 0.25, 0.01, 2.0, 10.0])
    unbounded, _ = sml_prediction(out, d, None, None)
    assert unbounded.flatten().tolist() == pytest.approx([0.0, 0.25, 0.005, 2.0, 20.0])


def test_inputs_it_cannot_take_are_refused_in_one_line() -> None:
    depth = torch.full((1, 1, 8, 8), 10.0)
    flat = torch.zeros(1, 1, 8, 8)
    for call, named in (
        (lambda: scale_scaffold(flat, depth), "quasi_dense: a frame whose scale map is constant"),
        (lambda: scale_scaffold(depth, depth * 0), "aligned: a depth that is not positive"),
        (lambda: scale_scaffold(depth[0], depth), "quasi_dense: shape [1, 8, 8]"),
        (lambda: sml_inputs(depth, depth[..., :4]), "aligned: shape [1, 1, 8, 4]"),
        (lambda: sml_loss(depth, depth, depth, loss_func="huber"), "loss_func='huber'"),
        (lambda: sml_loss(depth, depth, depth, w_smoothness=1.0), "image: the smoothness"),
    ):
        with pytest.raises(ArgumentError) as err:
            call()
        assert named in str(err.value) and "\n" not in str(err.value)


def test_the_learning_rate_follows_their_schedule() -> None:
    assert [learning_rate(e) for e in (1, 20, 21, EPOCHS)] == [
        LEARNING_RATES[0],
        LEARNING_RATES[0],
        LEARNING_RATES[1],
        LEARNING_RATES[1],
    ]
    with pytest.raises(ArgumentError, match="epoch=81"):
        learning_rate(81)


def test_the_sobel_filters() -> None:
    gx, gy = sobel_filter(3)
    assert gx[0, 0].tolist() == [[1, 0, -1], [2, 0, -2], [1, 0, -1]]
    assert gy[0, 0].tolist() == [[1, 2, 1], [0, 0, 0], [-1, -2, -1]]
    gx, _ = sobel_filter(7)
    assert gx[0, 0, 3].tolist() == [1, 1, 2, 0, -2, -1, -1]
    assert gx[0, 0, 0].tolist() == [1, 1, 1, 0, -1, -1, -1]


def _zeros(shape: list[int], key: str) -> torch.Tensor:
    dtype = torch.int64 if key.endswith("num_batches_tracked") else torch.float32
    return torch.zeros((), dtype=dtype).expand(shape)


def _layout_state(layout: dict) -> OrderedDict:
    """A state dict in the shipped layout: zero tensors (views of one value: a small file)."""
    return OrderedDict((k, _zeros(shape, k)) for k, shape in layout.items())


def test_the_shipped_layout_is_ours(layout, shipped) -> None:
    with torch.device("meta"):
        ours = ScaleMapLearner().state_dict()
    assert {k: list(t.shape) for k, t in ours.items()} == layout
    assert {k for k, t in ours.items() if t.dtype == torch.int64} == set(
        shipped["checkpoint"]["int64"]
    )
    wrote = shipped["their_training_wrote"]
    assert shipped["checkpoint"]["type"] == wrote["type"] == "OrderedDict"
    assert wrote["keys"] == len(layout) and wrote["files"] == ["model-1.pth"]


@pytest.mark.parametrize("form", ["flat", "model_and_optimizer", "lightning"])
def test_each_file_form_their_loader_reads_loads_strictly(
    tmp_path, layout, fresh_net, form
) -> None:
    """``BaseModel.load``'s three forms: the flat state dict their training writes, a dict of
    ``model`` and ``optimizer``, a Lightning checkpoint's ``model.`` keys (others ignored)."""
    state = _layout_state(layout)
    content = {
        "flat": state,
        "model_and_optimizer": {"model": state, "optimizer": {"state": {}, "param_groups": []}},
        "lightning": {
            "state_dict": {
                **{f"model.{k}": v for k, v in state.items()},
                "loss_fn.weight": torch.ones(2),
            },
            "epoch": 3,
        },
    }[form]
    path = tmp_path / "sml.ckpt"
    torch.save(content, path)
    for value in fresh_net.state_dict().values():
        value.fill_(1)
    assert load_released(fresh_net, path) == -1
    assert not any(bool(t.any()) for t in fresh_net.state_dict().values())  # the file's zeros


def _rename(state: dict) -> None:
    state["scratch.refinenet2.out_conv.weights"] = state.pop("scratch.refinenet2.out_conv.weight")


def _drop(state: dict) -> None:
    del state["pretrained.layer4.1.0.bn2.running_var"]


def _prefix(state: dict) -> None:
    for key in list(state):
        state[f"module.{key}"] = state.pop(key)


def _reshape(state: dict) -> None:
    state["first.0.weight"] = torch.zeros(3, 3, 3, 3)


@pytest.mark.parametrize(
    "edit, named",
    [
        (_rename, "unexpected key state_dict['scratch.refinenet2.out_conv.weights']"),
        (_drop, "missing key state_dict['pretrained.layer4.1.0.bn2.running_var']"),
        (_prefix, "unexpected key state_dict['module.first.0.weight']"),
        (_reshape, "state_dict['first.0.weight'] is [3, 3, 3, 3], expected [3, 2, 3, 3]"),
    ],
)
def test_a_renamed_missing_or_reshaped_key_fails_in_one_line_naming_it(
    tmp_path, layout, meta_net, edit, named
) -> None:
    state = _layout_state(layout)
    edit(state)
    path = tmp_path / "model-6000.pth"
    torch.save(state, path)
    with pytest.raises(ReleasedWeightsError) as err:
        load_released(meta_net, path)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"path={path}: not RadarCam-Depth's") and message.endswith(named)


def test_files_that_are_not_their_checkpoint_fail_in_one_line(tmp_path, meta_net) -> None:
    with pytest.raises(ArgumentFileError, match="no such file"):
        load_released(meta_net, tmp_path / "missing.pth")
    garbage = tmp_path / "notes.pth"
    garbage.write_text("not a checkpoint\n")
    with pytest.raises(ReleasedWeightsError, match=f"^path={garbage}: not a readable"):
        load_released(meta_net, garbage)
    other = tmp_path / "other.pth"
    torch.save({"network": {"G1.encoder.conv00.conv.weight": torch.zeros(2)}}, other)
    with pytest.raises(ReleasedWeightsError, match=r"unexpected key state_dict\['network'\]$"):
        load_released(meta_net, other)
    listed = tmp_path / "list.pth"
    torch.save([torch.zeros(2)], listed)
    with pytest.raises(ReleasedWeightsError, match="expected a state dict; it is a list$"):
        load_released(meta_net, listed)
    optimizer_only = tmp_path / "optimizer.pth"
    torch.save({"optimizer": {}, "epoch": 2}, optimizer_only)
    with pytest.raises(ReleasedWeightsError, match="its 'model' is a NoneType, not a state dict$"):
        load_released(meta_net, optimizer_only)
    hostile = tmp_path / "hostile.pth"
    torch.save({"first.0.weight": torch.zeros(3, 2, 3, 3), "args": argparse.Namespace()}, hostile)
    with pytest.raises(
        ReleasedWeightsError, match="refused to load; it holds a argparse.Namespace"
    ):
        load_released(meta_net, hostile)
