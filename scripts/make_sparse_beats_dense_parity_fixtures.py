"""Parity fixtures for :mod:`fusion_depth.models.sparse_beats_dense_released`, made by running
Sparse Beats Dense's authors' own code (github.com/megvii-research/Sparse-Beats-Dense,
Apache-2.0). Nothing of their code is copied here or into the repository: this script imports
it from a checkout at run time and keeps only what it computes.

The committed fixtures were made from commit 8b87d532942cafc8097df60486e94b0aebd8c2c1, with
torch 2.14.1 and numpy 2.4.6 on a 2-core Xeon CPU with two threads, nuscenes-devkit 1.1.10 and
pyquaternion 0.9.9 (their pins) and opencv-python-headless 5.1 (``fixtures.json`` records all
of it; the tests compare at the recorded thread count, since a convolution's rounding depends
on it). To make them again, from the repository root, in the project's environment::

    git clone https://github.com/megvii-research/Sparse-Beats-Dense CHECKOUT
    pip install --target EXTRA --no-deps "nuscenes-devkit==1.1.10" "pyquaternion==0.9.9" \\
        opencv-python-headless cachetools
    PYTHONPATH=EXTRA python scripts/make_sparse_beats_dense_parity_fixtures.py CHECKOUT

(``--no-deps``: their eval path needs only these beside torch, numpy, scipy and matplotlib.)

Their network has no argument: every width is fixed, and its 37 M values (148 MB) are too many
to keep. So the weights are not stored: :func:`fixture_weights` makes them from each key's name
and shape (a fixed hash, no random generator, so any torch makes the same bytes), scaled so
that activations keep their size through the layers; ``fixtures.json`` records their SHA-256,
and the test makes them again with this function. The frames are small instead: their
``forward_test`` pads every side to a multiple of 256, so a frame under 256 pixels runs at
256×256 (``G3``), 128×128 (``G2``) and 64×64 (``G1``). What it does:

1. Builds their ``model.Network`` and loads :func:`fixture_weights` into it (strict).
2. Frame ``eval``: writes a synthetic nuScenes frame in their ``data/`` layout (a 200×120
   ``CAM_FRONT`` image, a ``RADAR_FRONT`` ``.pcd`` in the devkit's binary format, a
   ``LIDAR_TOP`` ``.pcd.bin``, and an info pickle with the keys eval.py reads) in a temporary
   folder, and runs their ``eval.Vidar.__getitem__`` and ``Network.forward_test`` on it as
   ``Vidar.eval`` does. Its radar points (:data:`EVAL_POINTS`, placed by their pixel and depth)
   share a column, share a column at 1/2 and at 1/4 with other depths, lie on the borders,
   outside the image and behind the camera, and two are dropped by the devkit's filters.
3. Frame ``direct``: inputs given straight to ``forward_test``: 256×160 (a side that is a
   multiple of 256, padded by 256 more), 200 points with a count of 250 (a sweep of more than
   200 points, as eval.py hands it on), a radar map of whole columns.
4. Records their outputs (depth and valid mask, and ``G1``'s, the coarsest) in ``cases.pt``,
   and in ``shipped_layout.json`` the keys and shapes of their ``Network`` and the other
   entries of the checkpoint their ``train_DDP.py`` ``Session.save_checkpoint`` writes (after
   one AdamW step on zero gradients, as saved and read back with ``weights_only=True``; the
   learning rates are numpy float64 scalars, which plain ``weights_only`` loading refuses).

Outputs in ``--out`` (default ``tests/fixtures/sparse_beats_dense_authors``): ``cases.pt``,
``shipped_layout.json``, ``fixtures.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import math
import os
import pickle
import struct
import subprocess
import sys
import tempfile
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

AUTHORS_COMMIT = "8b87d532942cafc8097df60486e94b0aebd8c2c1"
SEED = 0
POOL_SIZE = 1_048_573  # a prime: the hashed values every tensor's values are read from
INPUT_SCALE = 1 / 128  # the encoders' first convolutions: their inputs are 0-255 and metres
POINT_SCALE = 1 / 4  # the point encoder's first layer: camera-frame metres

# Frame "eval": 200×120 image, its camera matrix and the nuScenes records (translation in m,
# rotation as a (w, x, y, z) quaternion, not quite unit as stored ones are not either).
EVAL_SIZE = (120, 200)
INTRINSIC = [[100.0, 0.0, 100.0], [0.0, 100.0, 60.0], [0.0, 0.0, 1.0]]
RECORDS = {
    "camera_calibrated_sensor": {
        "translation": [1.70, 0.016, 1.51],
        "rotation": [0.4998, -0.5031, 0.4998, -0.4972],
    },
    "camera_ego_pose": {"translation": [600.6, 1641.0, 0.0], "rotation": [0.571, 0.0, 0.0, 0.821]},
    "radar_calibrated_sensor": {
        "translation": [3.41, 0.0, 0.50],
        "rotation": [0.9999, 0.0, 0.0, 0.0131],
    },
    "radar_ego_pose": {"translation": [600.2, 1640.5, 0.0], "rotation": [0.57, 0.0, 0.0, 0.82]},
    "lidar_calibrated_sensor": {
        "translation": [0.94, 0.0, 1.84],
        "rotation": [0.707, 0, 0, -0.707],
    },
    "lidar_ego_pose": {"translation": [600.4, 1640.8, 0.0], "rotation": [0.5705, 0, 0, 0.8213]},
}
# Radar points as (u, v, camera depth z in m, invalid_state, dyn_prop): the pixel and depth
# each lands on. Columns 10 (twice: the later, 30 m, wins), 20 and 21 (one column at 1/2 and
# 1/4), 40-43 (one column at 1/4), both borders, below and right of the image, behind the
# camera (z < 0, projecting into the image), and two the devkit's filters drop.
EVAL_POINTS = [
    (10.5, 60.5, 12.0, 0, 1),
    (10.7, 80.5, 30.0, 0, 0),
    (20.5, 50.5, 8.0, 0, 1),
    (21.5, 70.5, 16.0, 0, 3),
    (40.5, 10.5, 45.0, 0, 1),
    (41.5, 20.5, 46.0, 0, 2),
    (42.5, 30.5, 47.0, 0, 1),
    (43.5, 40.5, 48.0, 0, 1),
    (0.5, 5.5, 2.0, 0, 1),
    (199.5, 60.5, 60.0, 0, 1),
    (150.5, 100.5, 3.5, 0, 6),
    (100.5, 130.5, 20.0, 0, 1),
    (250.5, 60.5, 25.0, 0, 1),
    (120.5, 60.5, -4.0, 0, 1),
    (70.5, 60.5, 15.0, 1, 1),
    (75.5, 60.5, 15.0, 0, 7),
]
# Frame "direct": size, radar columns, points kept of a sweep of this many.
DIRECT_SIZE = (256, 160)
DIRECT_COLUMNS = 40
DIRECT_COUNT = 250
PCD_FIELDS = (
    "x y z dyn_prop id rcs vx vy vx_comp vy_comp is_quality_valid ambig_state x_rms y_rms "
    "invalid_state pdh0 vx_rms vy_rms"
)
PCD_SIZES = "4 4 4 1 2 4 4 4 4 4 1 1 1 1 1 1 1 1"
PCD_TYPES = "F F F I I F F F F F I I I I I I I I"
PCD_PACK = "<fffbhfffffbbbbbbbb"


def _hashed(values: torch.Tensor) -> torch.Tensor:
    """A 32-bit integer hash of each value (int64 arithmetic that cannot overflow)."""
    x = values & 0xFFFFFFFF
    for _ in range(2):
        x = (((x >> 16) ^ x) * 0x45D9F3B) & 0xFFFFFFFF
    return (x >> 16) ^ x


def _pool(seed: int) -> torch.Tensor:
    """POOL_SIZE values in [-1, 1), float32: the hash of 0 … POOL_SIZE - 1 (and ``seed``)."""
    x = _hashed(torch.arange(POOL_SIZE, dtype=torch.int64) + seed * POOL_SIZE)
    return (x.to(torch.float64) / 2**31 - 1.0).to(torch.float32)


def fixture_weights(layout: Mapping[str, Sequence[int]], seed: int = SEED) -> dict[str, Any]:
    """The fixtures' weights for a state dict of keys and shapes (their ``Network``'s).

    Each tensor reads consecutive values of one pool of hashed values in [-1, 1) (wrapping at
    its end), from an offset given by the CRC-32 of its key: uniform-like, the same bytes with
    any torch. Convs,
    deconvs and linear layers: ``u · sqrt(3 / fan_in)`` (variance 1 / fan_in; the encoders'
    first convs times :data:`INPUT_SCALE`, the point encoder's first layer times
    :data:`POINT_SCALE`); biases ``0.1 u``; batch norms: weight ``1 + 0.25 u``, bias
    ``0.1 u``, running mean ``0.1 u``, running variance ``1 + 0.5 u``; ``num_batches_tracked``
    0."""
    pool = _pool(seed)
    pool = torch.cat([pool, pool])  # a tensor's values may run past the end: they wrap
    state: dict[str, Any] = {}
    for key, shape in layout.items():
        shape = tuple(shape)
        if key.endswith("num_batches_tracked"):
            state[key] = torch.zeros(shape, dtype=torch.int64)
            continue
        count = math.prod(shape)
        if count > POOL_SIZE:
            raise ValueError(f"{key}: {count} values, more than the pool's {POOL_SIZE}")
        offset = zlib.crc32(key.encode()) % POOL_SIZE
        u = pool[offset : offset + count].reshape(shape)
        module, name = key.rsplit(".", 2)[-2:]
        if module == "bn":
            scale, shift = {
                "weight": (0.25, 1.0),
                "bias": (0.1, 0.0),
                "running_mean": (0.1, 0.0),
                "running_var": (0.5, 1.0),
            }[name]
            state[key] = u * scale + shift
        elif name == "bias":
            state[key] = u * 0.1
        else:
            fan_in = shape[0] if module == "deconv" else count // shape[0]
            scale = math.sqrt(3.0 / fan_in)
            if key.endswith("encoder.conv00.conv.weight"):
                scale *= INPUT_SCALE
            if key == "calibrated_params_encoder.mlp.0.fully_connected.weight":
                scale *= POINT_SCALE
            state[key] = u * torch.tensor(scale, dtype=torch.float32)
    return state


def weights_digest(state: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 of the tensors' bytes, in key order."""
    digest = hashlib.sha256()
    for key in sorted(state):
        digest.update(key.encode())
        digest.update(state[key].contiguous().numpy().tobytes())
    return digest.hexdigest()


@contextlib.contextmanager
def _inside(folder: Path) -> Iterator[None]:
    """Run in ``folder``: their eval.py reads ``./data/nuscenes/samples/``."""
    before = Path.cwd()
    os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(before)


def import_authors(checkout: Path) -> dict[str, Any]:
    """Their modules, imported from the checkout (eval.py needs the devkit, cv2, pyquaternion)."""
    sys.path.insert(0, str(checkout))
    import eval as their_eval  # noqa: A004 - their module's name
    import model
    import utils
    from pyquaternion import Quaternion

    return {"eval": their_eval, "model": model, "utils": utils, "Quaternion": Quaternion}


def _camera_to_radar(authors: dict[str, Any], camera_points: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) taken back into the radar's frame (the inverse of their
    ``map_pointcloud1_to_pointcloud2``), to write them in the radar's file."""
    rotation = {n: authors["Quaternion"](r["rotation"]).rotation_matrix for n, r in RECORDS.items()}
    t = {n: np.array(r["translation"]) for n, r in RECORDS.items()}
    p = camera_points.T
    p = rotation["camera_calibrated_sensor"] @ p + t["camera_calibrated_sensor"][:, None]
    p = rotation["camera_ego_pose"] @ p + t["camera_ego_pose"][:, None]
    p = rotation["radar_ego_pose"].T @ (p - t["radar_ego_pose"][:, None])
    p = rotation["radar_calibrated_sensor"].T @ (p - t["radar_calibrated_sensor"][:, None])
    return p.T


def _write_pcd(path: Path, xyz: np.ndarray, states: Sequence[tuple[int, int]]) -> None:
    """A RADAR_FRONT file in nuScenes' binary PCD layout (what the devkit's from_file reads)."""
    header = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        f"FIELDS {PCD_FIELDS}",
        f"SIZE {PCD_SIZES}",
        f"TYPE {PCD_TYPES}",
        "COUNT " + " ".join(["1"] * 18),
        f"WIDTH {len(xyz)}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {len(xyz)}",
        "DATA binary",
    ]
    body = b"".join(
        struct.pack(PCD_PACK, *p, dyn, i, 5.0, 0.1, 0.2, 0.1, 0.2, 1, 3, 3, 3, invalid, 1, 3, 3)
        for i, (p, (invalid, dyn)) in enumerate(zip(xyz.tolist(), states, strict=True))
    )
    # The devkit asserts each field ends before the data does: real files end with a newline.
    path.write_bytes(("\n".join(header) + "\n").encode() + body + b"\n")


def _write_eval_frame(authors: dict[str, Any], root: Path, image: np.ndarray) -> Path:
    """The synthetic nuScenes frame and info pickle in their layout under ``root``."""
    import cv2

    samples = root / "data" / "nuscenes" / "samples"
    for channel in ("CAM_FRONT", "RADAR_FRONT", "LIDAR_TOP"):
        (samples / channel).mkdir(parents=True)
    cv2.imwrite(str(samples / "CAM_FRONT" / "frame.png"), image)  # lossless: what imread gives
    targets = np.array([p[:3] for p in EVAL_POINTS], dtype=np.float64)
    camera = np.linalg.inv(np.array(INTRINSIC)) @ np.stack(
        [targets[:, 0], targets[:, 1], np.ones(len(targets))]
    )
    camera = (camera * targets[:, 2]).T
    _write_pcd(
        samples / "RADAR_FRONT" / "frame.pcd",
        _camera_to_radar(authors, camera),
        [p[3:] for p in EVAL_POINTS],
    )
    lidar = np.array([[5.0, 1.0, 0.0, 10.0, 0.0], [12.0, -2.0, 0.5, 10.0, 0.0]], np.float32)
    lidar.tofile(samples / "LIDAR_TOP" / "frame.pcd.bin")
    cam, radar, lidar = (RECORDS[f"{s}_calibrated_sensor"] for s in ("camera", "radar", "lidar"))
    info = {
        "cam_infos": {
            "CAM_FRONT": {
                "filename": "samples/CAM_FRONT/frame.png",
                "calibrated_sensor": {**cam, "camera_intrinsic": INTRINSIC},
                "ego_pose": RECORDS["camera_ego_pose"],
            }
        },
        "radar_infos": {
            "RADAR_FRONT": [
                {
                    "data_path": "./data/nuscenes/samples/RADAR_FRONT/frame.pcd",
                    "sensor2ego_translation": radar["translation"],
                    "sensor2ego_rotation": radar["rotation"],
                    "ego2global_translation": RECORDS["radar_ego_pose"]["translation"],
                    "ego2global_rotation": RECORDS["radar_ego_pose"]["rotation"],
                }
            ]
        },
        "lidar_infos": {
            "LIDAR_TOP": {
                "filename": "samples/LIDAR_TOP/frame.pcd.bin",
                "calibrated_sensor": lidar,
                "ego_pose": RECORDS["lidar_ego_pose"],
            }
        },
    }
    path = root / "data" / "nuscenes_radar_5sweeps_infos_test.pkl"
    path.write_bytes(pickle.dumps([info]))
    return path


class Recorder:
    """Stands in for ``Network.forward`` and keeps the pyramids ``forward_test`` drops."""

    def __init__(self, net: Any) -> None:
        self.forward, self.pyramids = net.forward, None

    def __call__(self, *inputs: Any) -> Any:
        self.pyramids = self.forward(*inputs)
        return self.pyramids


def run_network(net: Any, img: Any, radar: Any, radar_pts: Any, count: Any) -> dict[str, Any]:
    """Their ``forward_test`` as ``Vidar.eval`` calls it: depth, valid, and G1's outputs."""
    recorder = Recorder(net)
    net.forward = recorder
    try:
        with torch.no_grad():
            depth, valid = net.forward_test(img, radar, radar_pts, count)
    finally:
        del net.forward
    preds, valids = recorder.pyramids
    return {
        "depth": torch.from_numpy(depth),
        "valid": torch.from_numpy(valid),
        "coarse_depth": preds[0],
        "coarse_valid": valids[0],
    }


def eval_frame(authors: dict[str, Any], net: Any, generator: np.random.Generator) -> dict:
    """Frame ``eval``: their ``Vidar.__getitem__`` and ``forward_test`` (step 2)."""
    from nuscenes.utils.data_classes import RadarPointCloud

    image = generator.integers(0, 256, (*EVAL_SIZE, 3), dtype=np.uint8)
    with tempfile.TemporaryDirectory() as folder, _inside(Path(folder)):
        infos = _write_eval_frame(authors, Path(folder), image)
        vidar = authors["eval"].Vidar(str(infos))
        img, radar_pts, count, radar, _ = vidar[0]  # lidar: their ground truth, unused here
        read = RadarPointCloud.from_file("data/nuscenes/samples/RADAR_FRONT/frame.pcd")
    net_inputs = tuple(x[None] for x in (img, radar, radar_pts, count))  # as Vidar.eval does
    return {
        "points_radar": torch.from_numpy(read.points[:3].T.copy()),
        "img": torch.from_numpy(net_inputs[0]),
        "radar": torch.from_numpy(net_inputs[1]),
        "radar_pts": torch.from_numpy(net_inputs[2]),
        "valid_radar_pts_cnt": torch.from_numpy(net_inputs[3]),
        **run_network(net, *net_inputs),
    }


def direct_frame(net: Any, generator: np.random.Generator) -> dict:
    """Frame ``direct``: inputs straight to ``forward_test`` (step 3)."""
    height, width = DIRECT_SIZE
    img = generator.integers(0, 256, (1, 3, height, width), dtype=np.uint8)
    row = np.zeros(width, np.float32)
    columns = generator.choice(width, DIRECT_COLUMNS, replace=False)
    row[columns] = generator.uniform(1.0, 80.0, DIRECT_COLUMNS).astype(np.float32)
    radar = np.ascontiguousarray(np.broadcast_to(row, (1, 1, height, width)))
    radar_pts = np.stack(
        [
            generator.uniform(-20, 20, 200),
            generator.uniform(-2, 2, 200),
            generator.uniform(1, 80, 200),
        ],
        axis=1,
    )[None]
    count = np.array([DIRECT_COUNT])
    return {
        "img": torch.from_numpy(img),
        "radar_row": torch.from_numpy(row),
        "radar_pts": torch.from_numpy(radar_pts),
        "valid_radar_pts_cnt": torch.from_numpy(count),
        **run_network(net, img, radar, radar_pts, count),
    }


def _as_json(value: Any) -> Any:
    """``value`` as JSON, each numpy scalar as ``{"numpy.float64": value}``."""
    if isinstance(value, np.generic):
        return {f"numpy.{type(value).__name__}": value.item()}
    if isinstance(value, Mapping):
        return {str(k): _as_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_as_json(v) for v in value]
    return value


def shipped_layout(authors: dict[str, Any]) -> dict[str, Any]:
    """Their ``Session.save_checkpoint`` entries for a fresh ``Network`` after one AdamW step
    (``train_DDP.py`` ``main``'s optimizer and scheduler: its learning rate function computes
    with ``np.cos``, so the rates are numpy float64 scalars), written and read back with
    ``weights_only=True`` and numpy's float64 scalars allowed (as ``load_released`` reads
    it): the network's keys and shapes, the other entries' values (the optimizer's
    per-parameter state summarised)."""
    from fusion_depth.models.sparse_beats_dense_released import NUMPY_FLOAT64_GLOBALS

    net = authors["model"].Network()
    opt = torch.optim.AdamW(net.parameters(), lr=1.0, weight_decay=4e-8)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda step: 3e-3 * (np.cos(step / 1000 * np.pi) + 1) * 0.5 + 1e-3
    )
    for p in net.parameters():
        p.grad = torch.zeros_like(p)
    opt.step()
    scheduler.step()
    clock = authors["utils"].TrainClock()
    clock.tick()
    saved = {
        "network": net.state_dict(),
        "clock": clock.make_checkpoint(),
        "optimizer": opt.state_dict(),
        "lr_scheduler": scheduler.state_dict(),
    }
    with tempfile.TemporaryDirectory() as folder:
        torch.save(saved, Path(folder) / "latest.ckpt")
        del saved, net, opt
        refused = torch.serialization.get_unsafe_globals_in_checkpoint(Path(folder) / "latest.ckpt")
        with torch.serialization.safe_globals(NUMPY_FLOAT64_GLOBALS):
            loaded = torch.load(Path(folder) / "latest.ckpt", weights_only=True)
    state = loaded["optimizer"]["state"]
    return {
        "refused_by_plain_weights_only": sorted(refused),
        "network": {k: list(t.shape) for k, t in loaded["network"].items()},
        "clock": loaded["clock"],
        "optimizer": {
            "state": {
                "parameters": len(state),
                "per_parameter": {
                    k: ("its parameter's shape" if v.dim() else [[], str(v.dtype)[6:]])
                    for k, v in state[0].items()
                },
            },
            "param_groups": [
                {**_as_json(g), "params": len(g["params"])}
                for g in loaded["optimizer"]["param_groups"]
            ],
        },
        "lr_scheduler": _as_json(loaded["lr_scheduler"]),
    }


def git_commit(checkout: Path) -> str:
    """The checkout's commit; refuses one with local changes."""
    done = subprocess.run(
        ["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True
    )
    if done.returncode:
        sys.exit(f"{checkout}: not a git checkout of the authors' repository (git rev-parse)")
    dirty = subprocess.run(
        ["git", "-C", str(checkout), "status", "--porcelain", "--untracked-files=no"],
        capture_output=True,
        text=True,
    ).stdout.strip()
    if dirty:
        sys.exit(f"{checkout}: has local changes; the fixtures must come from a commit")
    return done.stdout.strip()


def _cpu() -> str:
    """The CPU's model name (Linux), which with the thread count decides how convs round."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return "unknown"
    names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")]
    return names[0] if names else "unknown"


def _versions() -> dict[str, str]:
    from importlib.metadata import version

    packages = ("torch", "numpy", "nuscenes-devkit", "pyquaternion", "opencv-python-headless")
    return {name: version(name) for name in packages}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkout", type=Path, help="a git checkout of the authors' repository")
    parser.add_argument(
        "--out", type=Path, default=Path("tests/fixtures/sparse_beats_dense_authors")
    )
    args = parser.parse_args()
    commit = git_commit(args.checkout)
    out = args.out.resolve()
    authors = import_authors(args.checkout.resolve())
    net = authors["model"].Network()
    layout = {k: list(t.shape) for k, t in net.state_dict().items()}
    weights = fixture_weights(layout)
    net.load_state_dict(weights, strict=True)
    net.eval()  # as their Vidar.load_model
    generator = np.random.default_rng(SEED)
    cases = {"eval": eval_frame(authors, net, generator), "direct": direct_frame(net, generator)}
    out.mkdir(parents=True, exist_ok=True)
    torch.save(cases, out / "cases.pt")
    made = {
        "authors_commit": commit,
        "made_by": "scripts/make_sparse_beats_dense_parity_fixtures.py",
    }
    shipped = {**made, "checkpoint": shipped_layout(authors)}
    (out / "shipped_layout.json").write_text(json.dumps(shipped, separators=(",", ":")) + "\n")
    record = {
        **made,
        **_versions(),
        "threads": torch.get_num_threads(),
        "cpu": _cpu(),
        "seed": SEED,
        "weights_sha256": weights_digest(weights),
        "records": RECORDS,
        "intrinsic": INTRINSIC,
        "eval_points": EVAL_POINTS,
        "frames": {
            "eval": "their Vidar.__getitem__ and forward_test on a synthetic frame",
            "direct": "inputs straight to forward_test; radar_row is every row of the map",
        },
    }
    (out / "fixtures.json").write_text(json.dumps(record, indent=1) + "\n")
    for name, case in cases.items():
        depth, valid = case["depth"], case["valid"]
        print(
            f"{name}: depth {float(depth.min()):.3g}-{float(depth.max()):.3g} m "
            f"({float((depth == 0).float().mean()):.0%} zero), valid "
            f"{float(valid.min()):.3g}-{float(valid.max()):.3g}"
        )


if __name__ == "__main__":
    main()
