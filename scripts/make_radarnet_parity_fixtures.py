"""Parity fixtures for :mod:`fusion_depth.models.radarnet_released`, made by running RadarNet's
authors' own code (github.com/nesl/radar-camera-fusion-depth; Academic Software License, no
commercial use). Nothing of their code is copied here or into the repository: this script
imports it from a checkout at run time and keeps only what it computes.

The committed fixtures were made from commit c95c67dee85767be6b06d5f8540faf294d762ebb, with
torch 2.14.1 and torchvision 0.29.1 on a CPU, and Pillow 9.5.0 for the PNG round trip
(``fixtures.json`` records all of it). To make them again, from the repository root, in the
project's environment::

    git clone https://github.com/nesl/radar-camera-fusion-depth CHECKOUT
    python -m venv PNG_VENV && PNG_VENV/bin/pip install "pillow==9.5.0" "numpy<2" scipy
    python scripts/make_radarnet_parity_fixtures.py CHECKOUT --png-python PNG_VENV/bin/python

What it does, with random weights (seed 0) and small filter counts (the shipped FusionNet alone
is 58 MB):

1. Builds their ``RadarNetModel`` (``radarnetv1 batch_norm``, ``multiscale batch_norm``) and
   ``FusionNetModel`` (``fusionnet18 batch_norm``, ``weight_and_project``, ``multiscale
   batch_norm``, one resolution, depth in [1, 100] m, leaky ReLU) with the reduced sizes of
   ``STAGE1`` and ``STAGE2`` and their own random initialisation (seed 0). Their batch-norm
   statistics are measured on the frames (one pass in training mode) and their affine
   parameters drawn at random (:func:`calibrate`), and stage 1's last convolution is scaled by
   ``OUTPUT_SCALE``, so that confidences spread across the 0.5 threshold and some reach exactly
   1 (ties). Both are wrapped in ``DataParallel`` as their training scripts do and written with
   their own ``save_model`` (``association.pth``, ``fusion.pth``: the released files' layout,
   with a fresh Adam optimizer's state).
2. Runs stage 1 on the frames of ``FRAMES`` (points at the left and right image borders and
   inside, overlapping windows, a frame taller than the window, depths whose whole metres are
   other points' indices) as ``setup/setup_dataset_nuscenes_radarnet_test.py`` does: its main
   loop's steps (shift x by half the window, one box per point; the loop is not importable, it
   runs at import), their ``radarnet_transforms.Transforms`` and ``radarnet_main.forward``. A
   stand-in for the model keeps the confidences ``forward`` computes.
3. Writes the quasi-dense depth and response with their ``data_utils.save_depth`` /
   ``save_response`` and reads both back with ``load_depth``, as their FusionNet readers do
   (``datasets.FusionNetInferenceDataset``). Their pinned Pillow (9.0.1) writes these 32-bit
   ("I") images as 16-bit PNGs; the project's (13) refuses to. ``--png-python`` names an
   interpreter with a Pillow 9 (and numpy, scipy: ``data_utils`` imports them) that runs this
   step alone, in a subprocess.
4. Runs their FusionNet on the image and what step 3 read back (``fusionnet_main.run``'s steps:
   ``fusionnet_transforms.Transforms``, ``torch.cat([depth, response])``,
   ``FusionNetModel.forward``).
5. Builds both networks in their shipped configuration, writes them with ``save_model`` to a
   temporary folder and records every entry's keys, shapes and dtypes
   (``shipped_layout.json``); no weights of that size are kept.

``radarnet_main`` imports ``torch.utils.tensorboard`` for its training logs. Where TensorBoard is
not installed, a stand-in module without a working ``SummaryWriter`` takes its place for the run
(nothing here writes logs); no other import of theirs is replaced.

Outputs in ``--out`` (default ``tests/fixtures/radarnet_authors``): ``association.pth``,
``fusion.pth``, ``cases.pt`` (per frame: the image as 0-255 bytes, the points, their code's
confidences, depth, response, FusionNet's inputs and output depth), ``shipped_layout.json``,
``fixtures.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torchvision

SEED = 0
STAGE1 = {
    "patch_size": [100, 64],
    "image_filters": [8, 8, 16, 16, 16],
    "point_neurons": [8, 8, 16, 16, 16],
    "decoder_filters": [16, 16, 8, 8, 4],
}
STAGE2 = {
    "image_filters": [8, 8, 16, 16, 16, 16],
    "depth_filters": [4, 4, 8, 8, 8, 8],
    "decoder_filters": [16, 16, 16, 8, 8, 4],
    "min_depth": 1.0,
    "max_depth": 100.0,
}
# Frames (height, width, points (x, y, depth in m)). "border": x at both image borders and
# inside, overlapping windows; int(depth) of points 0, 3 and 5 are 3, 5 and 1, other points'
# indices, so the fill loop's chain rewrites them. "tall": a frame 8 rows taller than the window.
FRAMES = {
    "border": (
        100,
        160,
        [
            [0, 60, 3.6],
            [159, 40, 12.3],
            [80, 70, 7.9],
            [100, 55, 5.2],
            [30, 20, 40.0],
            [140, 90, 1.5],
        ],
    ),
    "tall": (108, 96, [[10, 50, 2.5], [50, 30, 20.0], [95, 80, 0.8]]),
}
# The shipped configurations (bash/run_radarnet_nuscenes.sh, bash/run_fusionnet_nuscenes_test.sh)
SHIPPED_STAGE1 = {
    "patch_size": [900, 288],
    "image_filters": [32, 64, 128, 128, 128],
    "point_neurons": [32, 64, 128, 128, 128],
    "decoder_filters": [256, 128, 64, 32, 16],
}
SHIPPED_STAGE2 = {
    "image_filters": [32, 64, 128, 256, 256, 256],
    "depth_filters": [16, 32, 64, 128, 128, 128],
    "decoder_filters": [256, 256, 128, 64, 64, 32],
    "min_depth": 1.0,
    "max_depth": 100.0,
}
CPU = torch.device("cpu")
OUTPUT_SCALE = 4.0  # stage 1's output0 weights, times this after their initialisation

# Step 3 in the PNG interpreter: argv = their src/, the folder, the frame names.
PNG_ROUND_TRIP = """
import sys
import numpy as np
import PIL
sys.path.insert(0, sys.argv[1])
import data_utils
folder = sys.argv[2]
for name in sys.argv[3:]:
    base = folder + "/" + name
    data_utils.save_depth(np.load(base + "_depth.npy"), base + "_depth.png")
    data_utils.save_response(np.load(base + "_response.npy"), base + "_response.png")
    for what in ("depth", "response"):
        loaded = data_utils.load_depth(base + "_" + what + ".png", data_format="CHW")
        np.save(base + "_" + what + "_in.npy", loaded.astype(np.float32))
print(PIL.__version__)
"""


def import_authors(src: Path) -> dict[str, Any]:
    """Their modules, imported from ``src`` (TensorBoard stood in for where it is missing)."""
    try:
        import torch.utils.tensorboard  # noqa: F401
    except ImportError:
        stand_in = types.ModuleType("torch.utils.tensorboard")

        class SummaryWriter:  # radarnet_main/fusionnet_main import it for training logs only
            def __init__(self, *args: Any, **kwargs: Any) -> None:
                raise RuntimeError("TensorBoard is not installed; no logs are written here")

        stand_in.SummaryWriter = SummaryWriter
        sys.modules["torch.utils.tensorboard"] = stand_in
    sys.path.insert(0, str(src))
    import fusionnet_model
    import fusionnet_transforms
    import radarnet_main
    import radarnet_model
    import radarnet_transforms

    return {
        "RadarNetModel": radarnet_model.RadarNetModel,
        "FusionNetModel": fusionnet_model.FusionNetModel,
        "radarnet_forward": radarnet_main.forward,
        "RadarNetTransforms": radarnet_transforms.Transforms,
        "FusionNetTransforms": fusionnet_transforms.Transforms,
    }


def build_stage1(authors: dict[str, Any], sizes: dict[str, Any]) -> Any:
    """Their RadarNetModel as run_radarnet.py builds it (bash/run_radarnet_nuscenes.sh)."""
    return authors["RadarNetModel"](
        input_channels_image=3,
        input_channels_depth=3,
        input_patch_size_image=sizes["patch_size"],
        encoder_type=["radarnetv1", "batch_norm"],
        n_filters_encoder_image=sizes["image_filters"],
        n_neurons_encoder_depth=sizes["point_neurons"],
        decoder_type=["multiscale", "batch_norm"],
        n_filters_decoder=sizes["decoder_filters"],
        weight_initializer="kaiming_uniform",
        activation_func="leaky_relu",
        device=CPU,
    )


def build_stage2(authors: dict[str, Any], sizes: dict[str, Any]) -> Any:
    """Their FusionNetModel as fusionnet_main.run builds it (run_fusionnet_nuscenes_test.sh)."""
    return authors["FusionNetModel"](
        input_channels_image=3,
        input_channels_depth=2,
        encoder_type=["fusionnet18", "batch_norm"],
        n_filters_encoder_image=sizes["image_filters"],
        n_filters_encoder_depth=sizes["depth_filters"],
        fusion_type="weight_and_project",
        decoder_type=["multiscale", "batch_norm"],
        n_resolution_decoder=1,
        n_filters_decoder=sizes["decoder_filters"],
        deconv_type="up",
        activation_func="leaky_relu",
        weight_initializer="kaiming_uniform",
        min_predict_depth=sizes["min_depth"],
        max_predict_depth=sizes["max_depth"],
        device=CPU,
    )


def batch_norms(model: Any) -> list[torch.nn.BatchNorm2d]:
    return [
        module
        for part in (model.encoder, model.decoder)
        for module in part.modules()
        if isinstance(module, torch.nn.BatchNorm2d)
    ]


def calibrate(model: Any, run: Callable[[], None], generator: torch.Generator) -> None:
    """Batch-norm statistics of ``model`` measured on the fixtures' frames (``run`` once in
    training mode, as a trained network's are measured on its data, so that activations keep
    their scale through the layers), then random affine parameters; ``model`` left in eval
    mode. At construction the statistics are 0 and 1, under which a random network's output
    hardly depends on its input."""
    for norm in batch_norms(model):
        norm.reset_running_stats()
        norm.momentum = None  # a plain average over the run
    model.train()
    run()
    model.eval()
    for norm in batch_norms(model):
        norm.momentum = 0.1
        with torch.no_grad():
            norm.weight.copy_(0.5 + torch.rand(norm.num_features, generator=generator))
            norm.bias.copy_(0.2 * torch.randn(norm.num_features, generator=generator))


def save_as_released(model: Any, path: Path, step: int) -> None:
    """Their save_model, after data_parallel() as in their training scripts."""
    model.data_parallel()
    model.save_model(str(path), step=step, optimizer=torch.optim.Adam(model.parameters()))


class Recorder:
    """Stands in for RadarNetModel in radarnet_main.forward and keeps the confidences."""

    def __init__(self, model: Any) -> None:
        self.model = model
        self.input_patch_size_image = model.input_patch_size_image
        self.confidences: torch.Tensor | None = None

    def forward(self, **inputs: Any) -> torch.Tensor:
        self.confidences = self.model.forward(**inputs)
        return self.confidences


def run_stage1(
    authors: dict[str, Any], model: Any, image: torch.Tensor, points: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Confidences, depth and response for one frame, as
    setup/setup_dataset_nuscenes_radarnet_test.py's main loop computes them."""
    image = image.float()[None]  # 1 x 3 x H x W, 0-255, as its DataLoader gives it
    radar_points = points.clone()
    pad_size_x = model.input_patch_size_image[1] // 2
    boxes = []
    for i in range(radar_points.shape[0]):  # the loop's steps: shift x, then the box
        radar_points[i, 0] = radar_points[i, 0] + pad_size_x
        box = torch.zeros(4)
        box[0] = radar_points[i, 0] - pad_size_x
        box[2] = radar_points[i, 0] + pad_size_x
        box[3] = image.shape[-2]
        boxes.append(box)
    transforms = authors["RadarNetTransforms"](normalized_image_range=[0, 1])
    [image], [radar_points], [boxes] = transforms.transform(
        images_arr=[image],
        points_arr=[radar_points],
        bounding_boxes_arr=[[torch.stack(boxes, dim=0)]],
        random_transform_probability=0.0,
    )
    recorder = Recorder(model)
    with torch.no_grad():
        depth, response = authors["radarnet_forward"](
            model=recorder,
            image=image,
            radar_points=radar_points,
            bounding_boxes_list=boxes,
            device=CPU,
        )
    return recorder.confidences, depth[0], response[0]


def png_round_trip(
    src: Path, python: str, maps: dict[str, tuple[torch.Tensor, torch.Tensor]]
) -> tuple[dict[str, torch.Tensor], str]:
    """FusionNet's depth inputs (2 x H x W) after their save_depth/save_response and
    load_depth, and the Pillow version that wrote the PNGs."""
    with tempfile.TemporaryDirectory() as folder:
        for name, (depth, response) in maps.items():
            # As the setup script hands them over: np.squeeze(tensor.cpu().numpy()).
            np.save(f"{folder}/{name}_depth.npy", np.squeeze(depth.numpy()))
            np.save(f"{folder}/{name}_response.npy", np.squeeze(response.numpy()))
        done = subprocess.run(
            [python, "-c", PNG_ROUND_TRIP, str(src), folder, *maps],
            capture_output=True,
            text=True,
        )
        if done.returncode:
            sys.exit(
                f"the PNG round trip failed in {python} (it needs a Pillow that writes mode-I "
                f"PNGs, such as 9.5.0, and numpy, scipy): {done.stderr.strip().splitlines()[-1]}"
            )
        inputs = {
            name: torch.from_numpy(
                np.concatenate(
                    [np.load(f"{folder}/{name}_{what}_in.npy") for what in ("depth", "response")]
                )
            )
            for name in maps
        }
    return inputs, done.stdout.strip()


def run_stage2(
    authors: dict[str, Any], model: Any, image: torch.Tensor, depth_input: torch.Tensor
) -> torch.Tensor:
    """FusionNet's depth for one frame, as fusionnet_main.run computes it."""
    image = image.float()[None]
    depth, response = depth_input[None, 0:1], depth_input[None, 1:2]
    transforms = authors["FusionNetTransforms"](normalized_image_range=[0, 1])
    [image] = transforms.transform(images_arr=[image], random_transform_probability=0.0)
    with torch.no_grad():
        return model.forward(image=image, input_depth=torch.cat([depth, response], dim=1))


def shipped_layout(authors: dict[str, Any]) -> dict[str, Any]:
    """Every entry of the files their save_model writes for the shipped configurations: the
    state dicts' keys with shape and dtype, the other entries' types."""
    layout = {}
    stages = (
        ("association", build_stage1, SHIPPED_STAGE1),
        ("fusion", build_stage2, SHIPPED_STAGE2),
    )
    with tempfile.TemporaryDirectory() as folder:
        for stage, build, sizes in stages:
            model = build(authors, sizes)
            path = Path(folder, f"{stage}.pth")
            save_as_released(model, path, step=0)
            del model
            entries = {}
            for entry, value in torch.load(path, weights_only=True).items():
                if entry.endswith("optimizer_state_dict"):
                    entries[entry] = "optimizer state (torch.optim.Adam.state_dict())"
                elif isinstance(value, dict):
                    entries[entry] = {
                        key: [list(t.shape), str(t.dtype).removeprefix("torch.")]
                        for key, t in value.items()
                    }
                else:
                    entries[entry] = type(value).__name__
            layout[stage] = {"sizes": sizes, "entries": entries}
    return layout


def git_commit(checkout: Path) -> str:
    done = subprocess.run(
        ["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True
    )
    if done.returncode:
        sys.exit(f"{checkout}: not a git checkout of the authors' repository (git rev-parse)")
    dirty = subprocess.run(
        ["git", "-C", str(checkout), "status", "--porcelain", "src"], capture_output=True, text=True
    ).stdout.strip()
    if dirty:
        sys.exit(f"{checkout}: src/ has local changes; the fixtures must come from a commit")
    return done.stdout.strip()


def make_frames(generator: torch.Generator) -> dict[str, dict[str, torch.Tensor]]:
    """Random 0-255 images (as uint8) and the points of FRAMES."""
    return {
        name: {
            "image": torch.randint(0, 256, (3, height, width), generator=generator).to(torch.uint8),
            "points": torch.tensor(points, dtype=torch.float32),
        }
        for name, (height, width, points) in FRAMES.items()
    }


def run_reference(
    authors: dict[str, Any], src: Path, png_python: str, generator: torch.Generator
) -> tuple[Any, Any, dict[str, dict[str, torch.Tensor]], str]:
    """Both stages built, calibrated and run on FRAMES (steps 1-4)."""
    frames = make_frames(generator)
    stage1 = build_stage1(authors, STAGE1)

    def run1() -> None:
        for frame in frames.values():
            out = run_stage1(authors, stage1, frame["image"], frame["points"])
            frame["confidences"], frame["depth"], frame["response"] = out

    calibrate(stage1, run1, generator)
    with torch.no_grad():  # logits of a few units, so that confidences spread across 0.5
        stage1.decoder.output0.conv.weight.mul_(OUTPUT_SCALE)
    run1()
    inputs, pillow = png_round_trip(
        src, png_python, {n: (f["depth"], f["response"]) for n, f in frames.items()}
    )
    stage2 = build_stage2(authors, STAGE2)

    def run2() -> None:
        for name, frame in frames.items():
            frame["fusion_input"] = inputs[name]
            frame["fusion_output"] = run_stage2(authors, stage2, frame["image"], inputs[name])[0]

    calibrate(stage2, run2, generator)
    run2()
    return stage1, stage2, frames, pillow


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkout", type=Path, help="a git checkout of the authors' repository")
    parser.add_argument("--png-python", default=sys.executable, help="Python with Pillow 9")
    parser.add_argument("--out", type=Path, default=Path("tests/fixtures/radarnet_authors"))
    args = parser.parse_args()
    commit, src = git_commit(args.checkout), args.checkout.resolve() / "src"
    authors = import_authors(src)
    torch.manual_seed(SEED)  # their layers' own initialisation
    generator = torch.Generator().manual_seed(SEED)
    stage1, stage2, frames, pillow = run_reference(authors, src, args.png_python, generator)
    args.out.mkdir(parents=True, exist_ok=True)
    save_as_released(stage1, args.out / "association.pth", step=1)
    save_as_released(stage2, args.out / "fusion.pth", step=2)
    torch.save(frames, args.out / "cases.pt")
    made = {"authors_commit": commit, "made_by": "scripts/make_radarnet_parity_fixtures.py"}
    layout = {**made, **shipped_layout(authors)}
    (args.out / "shipped_layout.json").write_text(json.dumps(layout, indent=1) + "\n")
    record = {
        **made,
        "torch": torch.__version__,
        "torchvision": torchvision.__version__,
        "pillow_png_round_trip": pillow,
        "seed": SEED,
        "association": STAGE1,
        "fusion": STAGE2,
        "frames": {n: {"height": h, "width": w} for n, (h, w, _) in FRAMES.items()},
        "stand_ins": [] if "tensorboard" in sys.modules else ["torch.utils.tensorboard"],
    }
    (args.out / "fixtures.json").write_text(json.dumps(record, indent=1) + "\n")
    for name, frame in frames.items():
        claimed = int((frame["response"] > 0).sum())
        print(
            f"{name}: {claimed}/{frame['response'].numel()} pixels claimed, depths "
            f"{torch.unique(frame['depth']).tolist()}, "
            f"{int((frame['confidences'] == 1).sum())} confidences of exactly 1"
        )


if __name__ == "__main__":
    main()
