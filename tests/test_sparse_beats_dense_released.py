"""Sparse Beats Dense's released network (:mod:`fusion_depth.models.sparse_beats_dense_released`)
against its authors' own code, on fixtures that code made (``tests/fixtures/
sparse_beats_dense_authors``, written by ``scripts/make_sparse_beats_dense_parity_fixtures.py``
from megvii-research/Sparse-Beats-Dense at the commit the fixtures record): the network's
weights load strictly from a file, its depth and valid mask equal theirs within 1e-5 relative
(fp32, CPU) on a frame their eval.py built and on one given straight to their
``forward_test``, the inputs built here are their eval.py's, the shipped checkpoint layout
(numpy learning rates included) loads strictly, and a file with a renamed, missing or
reshaped key, or no checkpoint at all, fails in one line naming it.

The fixtures hold no weights (their network has 37 M values and no width to reduce): the
script's ``fixture_weights`` makes them from the recorded layout, checked against the
recorded SHA-256."""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib.util
import json

import numpy as np
import pytest
import torch
from helpers import REPO

from fusion_depth.errors import ArgumentError, ArgumentFileError
from fusion_depth.models.sparse_beats_dense_released import (
    NUMPY_FLOAT64_GLOBALS,
    SEG_MASK_CLASSES,
    ReleasedWeightsError,
    SparseBeatsDense,
    downsample_depthmap,
    load_released,
    pad_to_released,
    radar_to_camera,
    released_depth,
    released_inputs,
    released_state,
    valid_label,
)
from fusion_depth.utils.checkpoint_file import CheckpointError, load_weights_only

FIXTURES = REPO / "tests" / "fixtures" / "sparse_beats_dense_authors"
SCRIPT = REPO / "scripts" / "make_sparse_beats_dense_parity_fixtures.py"
AUTHORS_COMMIT = "8b87d532942cafc8097df60486e94b0aebd8c2c1"
RTOL = 1e-5  # relative, no absolute slack: fp32 on a CPU, at the fixtures' thread count
# At another thread count the convolutions round otherwise: measured at one thread against the
# fixtures' two, on the same 2-core Xeon, 1.0e-4 m of depth and 2.9e-5 of the valid mask.
OTHER_THREADS_DEPTH_ATOL = 1e-3  # metres
OTHER_THREADS_VALID_ATOL = 2e-4
POINTS_ATOL = 1e-9  # metres: their numpy float64 chain against torch's, rounding apart


@functools.cache
def _script():
    """The fixtures' script, for its fixture_weights and weights_digest."""
    spec = importlib.util.spec_from_file_location("make_sbd_fixtures", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def _threads(count: int):
    """Run with ``count`` threads: how convolutions split their sums decides their rounding,
    so the fixtures compare bitwise only at the thread count that made them (pytest-xdist's
    workers run with one each)."""
    before = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@pytest.fixture(scope="module")
def record() -> dict:
    return json.loads((FIXTURES / "fixtures.json").read_text())


@pytest.fixture(scope="module")
def layout() -> dict:
    return json.loads((FIXTURES / "shipped_layout.json").read_text())["checkpoint"]


@pytest.fixture(scope="module")
def cases() -> dict[str, dict[str, torch.Tensor]]:
    return torch.load(FIXTURES / "cases.pt", weights_only=True)


@pytest.fixture(scope="module")
def net(record, layout, tmp_path_factory) -> SparseBeatsDense:
    """Ours, with the fixtures' weights loaded from a file in the released layout."""
    weights = _script().fixture_weights(layout["network"])
    assert _script().weights_digest(weights) == record["weights_sha256"]
    path = tmp_path_factory.mktemp("released") / "model.ckpt"
    torch.save({"network": weights, "clock": layout["clock"]}, path)
    del weights
    model = SparseBeatsDense()
    assert load_released(model, path) == layout["clock"]["step"]
    path.unlink()
    return model.eval()


def _frame_inputs(cases: dict, frame: str) -> tuple[torch.Tensor, ...]:
    """The network's inputs as their ``forward_test`` was given them (``direct``: the radar
    map is its one recorded row on every row)."""
    case = cases[frame]
    height = case["img"].shape[-2]
    radar = case["radar"] if frame == "eval" else case["radar_row"].expand(1, 1, height, -1)
    return case["img"], radar, case["radar_pts"], case["valid_radar_pts_cnt"]


@pytest.fixture(scope="module")
def ours(net, record, cases) -> dict[str, dict[str, torch.Tensor]]:
    """Our outputs per frame: :func:`released_depth`'s, and G1's (the coarsest) as it ran, at
    the fixtures' thread count."""
    outputs: dict[str, dict[str, torch.Tensor]] = {}
    seen: dict[str, tuple[torch.Tensor, ...]] = {}
    hook = net.G1.register_forward_hook(lambda module, inputs, out: seen.update(g1=out))
    try:
        with _threads(record["threads"]):
            for frame in cases:
                depth, valid = released_depth(net, *_frame_inputs(cases, frame))
                coarse_depth, coarse_valid, _ = seen["g1"]
                outputs[frame] = {
                    "depth": depth,
                    "valid": valid,
                    "coarse_depth": coarse_depth,
                    "coarse_valid": coarse_valid,
                }
    finally:
        hook.remove()
    return outputs


@pytest.fixture(scope="module")
def meta_net() -> SparseBeatsDense:
    """Ours without storage: enough to check a file's keys and shapes (nothing is copied)."""
    with torch.device("meta"):
        return SparseBeatsDense()


def test_the_fixtures_and_their_script_name_the_authors_commit(record) -> None:
    layout = json.loads((FIXTURES / "shipped_layout.json").read_text())
    assert record["authors_commit"] == layout["authors_commit"] == AUTHORS_COMMIT
    assert AUTHORS_COMMIT in SCRIPT.read_text()
    size = sum(path.stat().st_size for path in FIXTURES.iterdir())
    assert size < 1_500_000, f"the fixtures take {size} bytes"


@pytest.mark.parametrize("frame", ["eval", "direct"])
@pytest.mark.parametrize("output", ["depth", "valid"])
def test_depth_and_valid_mask_equal_the_authors(ours, cases, frame, output) -> None:
    torch.testing.assert_close(ours[frame][output], cases[frame][output], rtol=RTOL, atol=0)


@pytest.mark.parametrize("frame", ["eval", "direct"])
@pytest.mark.parametrize("output", ["coarse_depth", "coarse_valid"])
def test_the_coarsest_unets_outputs_equal_the_authors(ours, cases, frame, output) -> None:
    """G1's (1/4 of the padded frame): where a difference in the full outputs starts."""
    torch.testing.assert_close(ours[frame][output], cases[frame][output], rtol=RTOL, atol=0)


def test_the_fixtures_outputs_depend_on_the_radar_inputs(net, record, cases) -> None:
    """The comparison has power: with the radar map emptied, or one point counted instead of
    all, our depth moves from theirs by more than 100 times the tolerance."""
    img, radar, points, count = _frame_inputs(cases, "eval")
    theirs = cases["eval"]["depth"]
    for inputs in (
        (img, torch.zeros_like(radar), points, count),
        (img, radar, points, count * 0 + 1),
    ):
        with _threads(record["threads"]):
            depth, _ = released_depth(net, *inputs)
        assert not torch.allclose(depth, theirs, rtol=100 * RTOL, atol=0)


def _camera_points(record: dict, case: dict) -> torch.Tensor:
    """The fixture sweep's points in the camera frame, from the records their eval.py reads."""
    records = record["records"]
    return radar_to_camera(
        case["points_radar"],
        records["radar_calibrated_sensor"],
        records["radar_ego_pose"],
        records["camera_calibrated_sensor"],
        records["camera_ego_pose"],
    )


def test_the_inputs_built_here_are_their_eval_pys(record, cases) -> None:
    """From the radar sweep as the devkit read it, the records and the RGB image: their
    ``Vidar.__getitem__``'s image, radar map (whole columns, the later point of a column, a
    point behind the camera, the borders), padded points and count."""
    case = cases["eval"]
    points = _camera_points(record, case)
    count = int(case["valid_radar_pts_cnt"])
    torch.testing.assert_close(points, case["radar_pts"][0, :count], rtol=0, atol=POINTS_ATOL)
    ours = released_inputs(case["img"][0].flip(0), points, torch.tensor(record["intrinsic"]))
    assert torch.equal(ours["img"], case["img"])
    assert torch.equal(ours["radar"], case["radar"])
    assert torch.equal(ours["valid_radar_pts_cnt"], case["valid_radar_pts_cnt"])
    torch.testing.assert_close(ours["radar_pts"], case["radar_pts"], rtol=0, atol=POINTS_ATOL)
    column = case["radar"][0, 0, 0]
    assert float(column[10]) == 30.0 and float(column[120]) == -4.0  # later wins; behind


def test_the_fixture_frame_holds_the_cases_the_inputs_must_get_right(record, cases) -> None:
    """Points the devkit drops are not there; points outside the image count but draw no
    column; columns 20-21 and 40-43 share one column at 1/2 or 1/4, with other depths."""
    case = cases["eval"]
    kept = [p for p in record["eval_points"] if p[3] == 0 and p[4] < 7]
    assert int(case["valid_radar_pts_cnt"]) == len(kept) == case["points_radar"].shape[0]
    columns = (case["radar"][0, 0, 0] != 0).nonzero().flatten().tolist()
    assert {20, 21, 40, 41, 42, 43} <= set(columns) and len(columns) < len(kept)


def test_end_to_end_from_a_users_inputs_equals_the_authors(net, record, cases) -> None:
    case = cases["eval"]
    points = _camera_points(record, case)
    inputs = released_inputs(case["img"][0].flip(0), points, torch.tensor(record["intrinsic"]))
    with _threads(record["threads"]):
        depth, _ = released_depth(net, **inputs)
    torch.testing.assert_close(depth, case["depth"], rtol=RTOL, atol=0)


def test_at_one_thread_the_outputs_move_by_float_rounding_only(net, cases) -> None:
    """Another thread count (or CPU) rounds the convolutions otherwise: within the measured
    size, with margin (module docstring, "Differences")."""
    with _threads(1):
        depth, valid = released_depth(net, *_frame_inputs(cases, "direct"))
    theirs = cases["direct"]
    torch.testing.assert_close(depth, theirs["depth"], rtol=0, atol=OTHER_THREADS_DEPTH_ATOL)
    torch.testing.assert_close(valid, theirs["valid"], rtol=0, atol=OTHER_THREADS_VALID_ATOL)


def _as_saved(value):
    """A shipped_layout.json value as their checkpoint holds it (numpy scalars rebuilt)."""
    if isinstance(value, dict):
        if len(value) == 1 and next(iter(value)).startswith("numpy."):
            kind, number = next(iter(value.items()))
            return getattr(np, kind.removeprefix("numpy."))(number)
        return {k: _as_saved(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_as_saved(v) for v in value]
    return value


@functools.cache
def _parameter_shapes() -> tuple[tuple[int, ...], ...]:
    with torch.device("meta"):
        return tuple(tuple(p.shape) for p in SparseBeatsDense().parameters())


def _shipped_file(layout: dict, network: dict | None = None, optimizer: bool = True) -> dict:
    """Their training checkpoint's entries in the shipped layout: zero tensors (views of one
    value, so the file stays small), the optimizer's state per parameter, numpy rates."""
    if network is None:
        network = {k: _zeros(shape, k) for k, shape in layout["network"].items()}
    if not optimizer:
        return {"network": network, "clock": layout["clock"]}
    shapes = _parameter_shapes()
    assert len(shapes) == layout["optimizer"]["state"]["parameters"]
    state = {
        i: {"step": torch.tensor(1.0), "exp_avg": _zeros(s), "exp_avg_sq": _zeros(s)}
        for i, s in enumerate(shapes)
    }
    groups = [
        {**_as_saved(g), "params": list(range(g["params"]))}
        for g in layout["optimizer"]["param_groups"]
    ]
    return {
        "network": network,
        "clock": layout["clock"],
        "optimizer": {"state": state, "param_groups": groups},
        "lr_scheduler": _as_saved(layout["lr_scheduler"]),
    }


def _zeros(shape: list[int], key: str = "") -> torch.Tensor:
    dtype = torch.int64 if key.endswith("num_batches_tracked") else torch.float32
    return torch.zeros((), dtype=dtype).expand(shape)


@pytest.fixture(scope="module")
def training_file(layout, tmp_path_factory):
    """A file as their ``Session.save_checkpoint`` writes it, in the shipped layout."""
    path = tmp_path_factory.mktemp("shipped") / "model.ckpt"
    torch.save(_shipped_file(layout), path)
    return path


def test_the_shipped_layout_is_ours_and_its_training_checkpoint_loads_strictly(
    training_file, layout
) -> None:
    net = SparseBeatsDense()
    assert {k: list(t.shape) for k, t in net.state_dict().items()} == layout["network"]
    assert load_released(net, training_file) == layout["clock"]["step"]
    assert not any(bool(t.any()) for t in net.state_dict().values())  # the file's zeros


def test_plain_weights_only_loading_refuses_their_training_checkpoint(
    training_file, layout
) -> None:
    """Why the loader allows numpy's float64: their learning rates are numpy scalars, which
    numpy 1 (their pin) and 2 pickle under two names; the loader allows both."""
    refused = layout["refused_by_plain_weights_only"]
    assert "numpy.dtype" in refused and any(n.endswith("multiarray.scalar") for n in refused)
    with pytest.raises(CheckpointError, match=r"numpy\._?core\.multiarray\.scalar"):
        load_weights_only(training_file)
    allowed = {
        name for entry in NUMPY_FLOAT64_GLOBALS if isinstance(entry, tuple) for name in entry[1:]
    }
    assert allowed == {"numpy.core.multiarray.scalar", "numpy._core.multiarray.scalar"}


def _edited_file(tmp_path, layout, edit) -> object:
    network = {k: _zeros(shape, k) for k, shape in layout["network"].items()}
    edit(network)
    path = tmp_path / "model.ckpt"
    torch.save(_shipped_file(layout, network, optimizer=False), path)
    return path


def _rename(state: dict) -> None:
    state["G2.encoder.g4_3.conv_3x3.conv.weights"] = state.pop(
        "G2.encoder.g4_3.conv_3x3.conv.weight"
    )


def _drop(state: dict) -> None:
    del state["calibrated_params_encoder.mlp.5.fully_connected.bias"]


def _prefix(state: dict) -> None:
    for key in list(state):
        state[f"module.{key}"] = state.pop(key)


@pytest.mark.parametrize(
    "edit, named",
    [
        (_rename, "unexpected key network['G2.encoder.g4_3.conv_3x3.conv.weights']"),
        (_drop, "missing key network['calibrated_params_encoder.mlp.5.fully_connected.bias']"),
        (_prefix, "unexpected key network['module.G1.encoder.conv00.conv.weight']"),
    ],
)
def test_a_renamed_or_missing_key_fails_in_one_line_naming_it(
    tmp_path, layout, meta_net, edit, named
) -> None:
    path = _edited_file(tmp_path, layout, edit)
    with pytest.raises(ReleasedWeightsError) as err:
        load_released(meta_net, path)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"path={path}: ") and message.endswith(named)


def test_a_reshaped_key_is_named_with_both_shapes(tmp_path, layout, meta_net) -> None:
    def reshape(state: dict) -> None:
        state["G3.resize5.deconv.weight"] = torch.zeros(8, 2, 2, 2)

    path = _edited_file(tmp_path, layout, reshape)
    with pytest.raises(
        ReleasedWeightsError,
        match=r"network\['G3\.resize5\.deconv\.weight'\] is \[8, 2, 2, 2\], expected "
        r"\[8, 1, 2, 2\]$",
    ):
        load_released(meta_net, path)


def test_files_that_are_not_the_released_checkpoint_fail_in_one_line(tmp_path, meta_net) -> None:
    net = meta_net
    with pytest.raises(ArgumentFileError, match="no such file"):
        load_released(net, tmp_path / "missing.ckpt")
    garbage = tmp_path / "notes.ckpt"
    garbage.write_text("not a checkpoint\n")
    with pytest.raises(ReleasedWeightsError, match=f"^path={garbage}: not a readable"):
        load_released(net, garbage)
    other = tmp_path / "other.ckpt"
    torch.save({"state_dict": {"encoder.weight": torch.zeros(2)}, "epoch": 3}, other)
    with pytest.raises(
        ReleasedWeightsError, match=f"^path={other}: .*'network' dict; it holds state_dict, epoch$"
    ):
        load_released(net, other)
    hostile = tmp_path / "hostile.ckpt"
    torch.save({"network": {}, "args": argparse.Namespace(lr=1e-3)}, hostile)
    with pytest.raises(
        ReleasedWeightsError, match="refused to load; it holds a argparse.Namespace"
    ):
        load_released(net, hostile)


def test_downsampling_keeps_the_last_nonzero_pixel_in_row_major_order() -> None:
    depth = torch.zeros(1, 1, 4, 4)
    depth[0, 0, :, 0] = 5.0  # column 0
    depth[0, 0, :, 1] = 7.0  # column 1: the same coarse column at 1/2, later in each row
    depth[0, 0, 3, 2] = -2.0  # a negative depth is non-zero too
    out = downsample_depthmap(depth, 0.5)
    assert out[0, 0, :, 0].tolist() == [7.0, 7.0] and out[0, 0, :, 1].tolist() == [0.0, -2.0]
    depth[0, 0, 1, 1] = 0.0  # row 1 of the first block keeps column 0's value
    assert float(downsample_depthmap(depth, 0.5)[0, 0, 0, 0]) == 5.0
    assert float(downsample_depthmap(depth, 0.25)[0, 0, 0, 0]) == -2.0


def test_more_than_200_points_keep_200_in_order_and_count_all() -> None:
    points = torch.stack([torch.zeros(250), torch.zeros(250), torch.arange(1.0, 251.0)], dim=1)
    inputs = released_inputs(
        torch.zeros(3, 8, 8, dtype=torch.uint8),
        points,
        torch.eye(3),
        generator=torch.Generator().manual_seed(0),
    )
    kept = inputs["radar_pts"][0, :, 2]
    assert kept.shape == (200,) and bool((kept.diff() > 0).all())
    assert int(inputs["valid_radar_pts_cnt"]) == 250


def _depth_of(radar_shape: tuple[int, ...], count: int):
    def call(net: SparseBeatsDense) -> object:
        img, points = torch.zeros(1, 3, 8, 8), torch.zeros(1, 200, 3)
        return released_depth(net, img, torch.zeros(radar_shape), points, torch.tensor([count]))

    return call


@pytest.mark.parametrize(
    "call, named",
    [
        (
            lambda net: released_inputs(torch.zeros(3, 4, 4), torch.zeros(0, 3), torch.eye(3)),
            "points: shape [0, 3]",
        ),
        (
            lambda net: released_inputs(torch.zeros(4, 4, 3), torch.ones(1, 3), torch.eye(3)),
            "image: shape [4, 4, 3]",
        ),
        (_depth_of((1, 1, 8, 8), 0), "valid_radar_pts_cnt: a frame without radar points"),
        (_depth_of((1, 1, 8, 9), 1), "radar: shape [1, 1, 8, 9], expected [1, 1, 8, 8]"),
    ],
)
def test_inputs_it_cannot_take_are_refused_in_one_line(meta_net, call, named) -> None:
    with pytest.raises(ArgumentError) as err:
        call(meta_net)
    assert named in str(err.value) and "\n" not in str(err.value)


def test_padding_adds_up_to_a_multiple_of_256_and_never_nothing() -> None:
    """``Network.padding``: 900×1600 (nuScenes) runs at 1024×1792; 256 rows get 256 more."""
    for (h, w), padded in {(900, 1600): (1024, 1792), (256, 255): (512, 256)}.items():
        x = torch.ones(1, 1, h, w)
        out = pad_to_released(x)
        assert tuple(out.shape[-2:]) == padded and float(out.sum()) == h * w
        assert torch.equal(out[..., :h, :w], x)


def test_a_sweep_with_no_point_in_the_image_gives_an_empty_map() -> None:
    behind = torch.tensor([[0.0, 0.0, 5.0]])
    inputs = released_inputs(
        torch.zeros(3, 8, 8), behind, torch.tensor([[1.0, 0, 100], [0, 1, 4], [0, 0, 1]])
    )
    assert not inputs["radar"].any() and int(inputs["valid_radar_pts_cnt"]) == 1


def test_the_valid_label_marks_the_authors_classes() -> None:
    mask = torch.arange(150, dtype=torch.uint8).reshape(10, 15)
    label = valid_label(mask)
    assert label.shape == (1, 10, 15) and label.dtype == torch.float32
    assert set(mask[label[0] == 1].tolist()) == set(SEG_MASK_CLASSES)


def test_released_state_maps_the_file_key_for_key(layout, meta_net) -> None:
    network = {k: _zeros(shape, k) for k, shape in layout["network"].items()}
    state = released_state({"network": network}, meta_net)
    assert state.keys() == network.keys()
