"""Fuzzing the dataset readers (issue 6, "bad input gets a clear answer").

Valid files are written with the platform's own writers (depth_io, CARLA's encoder and the
recorder script, numpy.save, prepare_split), then damaged: truncated, bytes flipped or
overwritten (with the PNG checksums repaired, so the damage reaches the decoder), re-encoded at
another bit depth or colour type, given absurd sizes, NaN/inf and junk in radar and metadata
files. Every reader must either return a well-formed array (dtype, shape, finite where it must
be) or raise DataFileError whose message starts with the file's path; any other exception, or a
reader running past a time limit, fails. Finally a real CARLA split with one damaged frame goes
through a DataLoader worker: the main process gets DataFileError naming the file, not a dead
worker or a timeout.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import shutil
import signal
import struct
import warnings
import zlib
from collections import namedtuple
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.carla import H as CARLA_H
from helpers.carla import W as CARLA_W
from helpers.carla import record_fixture, recorder
from helpers.topview import write_folder
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from PIL import Image
from torch.utils.data import DataLoader

from fusion_depth.data.cache import PreparedFrame, PreparedSplit, prepare_split
from fusion_depth.data.carla import (
    CONDITIONS,
    RADAR_COLUMNS,
    CarlaDepth,
    decode_carla_depth,
    encode_carla_depth,
    project_radar,
    read_carla_depth,
    read_frame_meta,
    read_radar_csv,
    transform_matrix,
)
from fusion_depth.data.depth_io import (
    DataFileError,
    read_depth_png,
    read_rgb,
    write_depth_png,
    write_rgb_png,
)
from fusion_depth.data.topview import TopViewDepth, read_depth_file

# Sized for well under a minute on two shared cores (FUZZ_READERS_EXAMPLES=5000 for a deeper
# run by hand); `database=None`: no example database is kept between runs.
FUZZ = settings(
    max_examples=int(os.environ.get("FUZZ_READERS_EXAMPLES", "100")),
    deadline=timedelta(seconds=10),
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
READ_LIMIT_S = 20.0  # one read of a file of a few hundred bytes: far beyond any sane time
DEPTH_PNG_MAX = 65535 / 256  # the largest metres a uint16 x 256 depth PNG holds
FLOAT32_MAX = float(np.finfo(np.float32).max)
CARLA_FAR = 1000.0

Detection = namedtuple("Detection", RADAR_COLUMNS)  # what recorder.write_radar reads


# --- harness ----------------------------------------------------------------------------------


class Hung(BaseException):
    """A read ran past READ_LIMIT_S. A BaseException, so a reader's ``except Exception`` cannot
    turn it into a DataFileError and hide the hang."""


@contextlib.contextmanager
def time_limit(seconds: float = READ_LIMIT_S):
    def alarm(signum, frame):
        raise Hung(f"still reading after {seconds} s")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def outcome(read, path: Path, *args):
    """``read(path, *args)``, or None when it raised DataFileError naming ``path`` first. Any
    other exception propagates and fails the test."""
    try:
        with time_limit():
            return read(path, *args)
    except DataFileError as err:
        assert str(err).startswith(f"{path}: "), str(err)
        assert err.path == path
        assert len(str(err)) > len(f"{path}: ") + 10  # says what was expected
        return None


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """One folder for the examples of the @given tests (a space in it: paths are quoted
    nowhere, messages must still start with them)."""
    path = tmp_path_factory.mktemp("fuzz") / "frame files"
    path.mkdir()
    return path


def write_bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


# --- damage -----------------------------------------------------------------------------------


def repair_png_crcs(data: bytes) -> bytes:
    """Recomputes every complete chunk's CRC, so damage gets past Pillow's checksum test and
    reaches the header parser and the decoder."""
    out = bytearray(data)
    pos = 8
    while pos + 12 <= len(out):
        (length,) = struct.unpack(">I", out[pos : pos + 4])
        end = pos + 8 + length
        if end + 4 > len(out):
            break
        out[end : end + 4] = struct.pack(">I", zlib.crc32(bytes(out[pos + 4 : end])))
        pos = end + 4
    return bytes(out)


@st.composite
def damaged(draw, data: bytes, png: bool = False) -> bytes:
    """``data`` truncated, with bytes flipped, overwritten, deleted or inserted; for a PNG the
    chunk CRCs are repaired or not."""
    kind = draw(st.sampled_from(["truncate", "flip", "overwrite", "delete", "insert"]))
    n = len(data)
    if kind == "truncate":
        return data[: draw(st.integers(0, n - 1))]
    out = bytearray(data)
    if kind == "flip":
        for _ in range(draw(st.integers(1, 6))):
            out[draw(st.integers(0, n - 1))] ^= draw(st.integers(1, 255))
    elif kind == "overwrite":
        at = draw(st.integers(0, n - 1))
        junk = draw(st.binary(min_size=1, max_size=24))
        out[at : at + len(junk)] = junk
    elif kind == "delete":
        at = draw(st.integers(0, n - 1))
        del out[at : at + draw(st.integers(1, 32))]
    else:
        at = draw(st.integers(0, n))
        out[at:at] = draw(st.binary(min_size=1, max_size=24))
    if png and draw(st.booleans()):
        return repair_png_crcs(bytes(out))
    return bytes(out)


def png_header_intact(original: bytes, data: bytes) -> bool:
    """Signature and IHDR (the first 33 bytes) unchanged: the decoded size must be the same."""
    return len(data) >= 33 and data[:33] == original[:33]


# --- a PNG encoder for what Pillow will not write (16-bit colour, 2/4-bit grey, lying headers)


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def encode_png(
    pixels: np.ndarray,
    bit_depth: int,
    colour_type: int,
    palette: np.ndarray | None = None,
    size: tuple[int, int] | None = None,
) -> bytes:
    """A PNG of ``pixels`` ((H, W) or (H, W, C) values < 2**bit_depth), written by hand from the
    PNG specification; ``size`` = (width, height) puts other dimensions in the header."""
    pixels = np.asarray(pixels)
    h, w = pixels.shape[:2]
    channels = pixels.reshape(h, w, -1).shape[2]
    if bit_depth == 16:
        rows = pixels.astype(">u2").reshape(h, w * channels).view(np.uint8)
    elif bit_depth == 8:
        rows = pixels.astype(np.uint8).reshape(h, w * channels)
    else:
        shifts = np.arange(bit_depth - 1, -1, -1, dtype=np.uint8)
        bits = (pixels.astype(np.uint8).reshape(h, w)[..., None] >> shifts) & 1
        rows = np.packbits(bits.reshape(h, w * bit_depth), axis=1)
    raw = b"".join(b"\x00" + row.tobytes() for row in rows)  # filter type 0 on every row
    width, height = size or (w, h)
    header = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    out = b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", header)
    if palette is not None:
        out += png_chunk(b"PLTE", np.asarray(palette, np.uint8).tobytes())
    return out + png_chunk(b"IDAT", zlib.compress(raw)) + png_chunk(b"IEND", b"")


CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # PNG colour type: grey, RGB, palette, grey+alpha, RGBA
PNG_KINDS = [(0, b) for b in (1, 2, 4, 8, 16)] + [(3, b) for b in (1, 2, 4, 8)]
PNG_KINDS += [(c, b) for c in (2, 4, 6) for b in (8, 16)]


@st.composite
def png_images(draw):
    """(colour type, bit depth, pixels, palette) of a valid PNG of any kind the format has."""
    colour_type, bits = draw(st.sampled_from(PNG_KINDS))
    h, w = draw(st.integers(1, 8)), draw(st.integers(1, 8))
    shape = (h, w) if CHANNELS[colour_type] == 1 else (h, w, CHANNELS[colour_type])
    dtype = np.uint16 if bits == 16 else np.uint8
    pixels = draw(hnp.arrays(dtype, shape, elements=st.integers(0, 2**bits - 1)))
    palette = None
    if colour_type == 3:
        palette = draw(hnp.arrays(np.uint8, (2**bits, 3)))
    return colour_type, bits, pixels, palette


def expected_rgb(colour_type: int, bits: int, pixels: np.ndarray, palette) -> np.ndarray | None:
    """What an exact conversion to 8-bit RGB gives (None: there is none, a DataFileError)."""
    high = pixels >> 8 if bits == 16 else pixels  # 16-bit colour keeps each value's high byte
    if colour_type == 0:
        if bits == 16:
            return None  # a 16-bit single channel is a depth map, not a camera image
        grey = pixels.astype(np.int64) * 255 // (2**bits - 1)
        return np.repeat(grey[..., None], 3, axis=2).astype(np.uint8)
    if colour_type == 3:
        return palette[pixels]
    if colour_type == 4:
        return np.repeat(high[..., :1], 3, axis=2).astype(np.uint8)
    return high[..., :3].astype(np.uint8)


# --- images: damaged files --------------------------------------------------------------------


def _rgb_file(image: np.ndarray, path: Path) -> bytes:
    write_rgb_png(path, image)
    return path.read_bytes()


def _depth_file(image: np.ndarray, path: Path) -> bytes:
    write_depth_png(path, image[..., 0].astype(np.float64) * 0.9 + image[..., 1] / 7.0)
    return path.read_bytes()


def _carla_file(image: np.ndarray, path: Path) -> bytes:
    depth = image[..., 0].astype(np.float64) * 3.7 + image[..., 1] / 11.0 + image[..., 2] / 300
    write_rgb_png(path, encode_carla_depth(depth))
    return path.read_bytes()


def _check_rgb(array: np.ndarray) -> None:
    assert array.dtype == np.uint8 and array.ndim == 3 and array.shape[2] == 3


def _check_depth(array: np.ndarray) -> None:
    assert array.dtype == np.float32 and array.ndim == 2
    assert np.isfinite(array).all() and array.min() >= 0 and array.max() <= DEPTH_PNG_MAX


def _check_carla(array: np.ndarray) -> None:
    assert array.dtype == np.float64 and array.ndim == 2
    assert np.isfinite(array).all() and array.min() >= 0 and array.max() <= CARLA_FAR + 1e-9


IMAGE_READERS = {
    "rgb": (_rgb_file, read_rgb, _check_rgb),
    "depth_png": (_depth_file, read_depth_png, _check_depth),
    "carla_depth": (_carla_file, read_carla_depth, _check_carla),
}


@pytest.mark.parametrize("reader", list(IMAGE_READERS))
@FUZZ
@given(
    image=hnp.arrays(np.uint8, st.tuples(st.integers(1, 12), st.integers(1, 12), st.just(3))),
    data=st.data(),
)
def test_damaged_png_loads_or_fails_naming_the_file(workdir, reader, image, data) -> None:
    make, read, check = IMAGE_READERS[reader]
    path = workdir / f"{reader}.png"
    original = make(image, path)
    pristine = outcome(read, path)
    assert pristine is not None and pristine.shape[:2] == image.shape[:2]
    mutated = data.draw(damaged(original, png=True), label="damaged file")
    result = outcome(read, write_bytes(path, mutated))
    if result is None:
        return
    check(result)
    if png_header_intact(original, mutated):
        assert result.shape[:2] == image.shape[:2]
    if mutated == original:
        np.testing.assert_array_equal(result, pristine)


# --- images: every PNG colour type and bit depth ------------------------------------------------


@FUZZ
@given(png=png_images())
def test_png_bit_depths_and_modes_convert_exactly_or_fail(workdir, png) -> None:
    colour_type, bits, pixels, palette = png
    path = write_bytes(workdir / "kind.png", encode_png(pixels, bits, colour_type, palette))
    kind = f"colour type {colour_type}, {bits} bits"

    expected = expected_rgb(colour_type, bits, pixels, palette)
    rgb = outcome(read_rgb, path)
    if expected is None:
        assert rgb is None, f"{kind}: read as an image"
    else:
        assert rgb is not None, f"{kind}: refused as an image"
        np.testing.assert_array_equal(rgb, expected)

    depth = outcome(read_depth_png, path)
    if (colour_type, bits) == (0, 16):  # the only exact depth encoding
        np.testing.assert_array_equal(depth, pixels.astype(np.float32) / np.float32(256))
        assert depth.dtype == np.float32
    else:
        assert depth is None, f"{kind}: read as a 16-bit depth PNG"

    carla = outcome(read_carla_depth, path)
    colour = pixels[..., :3] if colour_type in (2, 6) else None
    grey = colour is not None and (colour == colour[..., :1]).all() and np.unique(colour).size > 1
    if colour_type in (2, 6) and bits == 8 and not grey:  # CARLA's 8-bit R, G, B codes
        np.testing.assert_array_equal(carla, decode_carla_depth(colour.astype(np.uint8)))
    else:
        assert carla is None, f"{kind}: read as CARLA's depth encoding"


_RNG = np.random.default_rng(0)
PIL_ARRAYS = {  # Pillow infers the mode from dtype and shape
    "1": _RNG.integers(0, 2, (5, 7)).astype(bool),
    "L": _RNG.integers(0, 256, (5, 7), dtype=np.uint8),
    "LA": _RNG.integers(0, 256, (5, 7, 2), dtype=np.uint8),
    "RGBA": _RNG.integers(0, 256, (5, 7, 4), dtype=np.uint8),
    "I;16": _RNG.integers(0, 65536, (5, 7), dtype=np.uint16),
    "I": _RNG.integers(-(2**31), 2**31 - 1, (5, 7), dtype=np.int32),
    "F": _RNG.normal(0, 1e3, (5, 7)).astype(np.float32),
}


def _pillow_writes(mode: str, fmt: str) -> bool:
    try:
        Image.fromarray(PIL_ARRAYS[mode]).save(io.BytesIO(), format=fmt)
    except (OSError, ValueError, KeyError):
        return False
    return True


FORMAT_CASES = [
    (mode, fmt)
    for mode in PIL_ARRAYS
    for fmt in ("PNG", "TIFF", "JPEG", "BMP", "GIF")
    if _pillow_writes(mode, fmt)
]


@pytest.mark.parametrize("mode,fmt", FORMAT_CASES)
def test_other_formats_under_a_png_name_are_read_exactly_or_refused(tmp_path, mode, fmt) -> None:
    """What Pillow writes in other formats and modes, all named .png: a camera image is read when
    an exact RGB exists (JPEG: lossy, so only its shape), the depth readers take only what they
    decode exactly, 16/32-bit single-channel and float images are no camera images."""
    path = tmp_path / "frame.png"
    Image.fromarray(PIL_ARRAYS[mode]).save(path, format=fmt)
    stored = Image.open(path)
    stored.load()
    values = np.asarray(stored)
    rgb = outcome(read_rgb, path)
    if stored.mode in ("I;16", "I;16B", "I", "F"):
        assert rgb is None
    elif fmt == "JPEG":
        assert rgb is not None and rgb.shape == (5, 7, 3)
    else:
        np.testing.assert_array_equal(rgb, np.asarray(stored.convert("RGB")))
    depth = outcome(read_depth_png, path)
    if stored.mode in ("I;16", "I;16B", "I") and 0 <= values.min() and values.max() <= 65535:
        np.testing.assert_array_equal(depth, values.astype(np.float32) / 256)
    else:
        assert depth is None
    carla = outcome(read_carla_depth, path)
    if (mode, fmt) == ("RGBA", "PNG"):
        np.testing.assert_array_equal(carla, decode_carla_depth(PIL_ARRAYS[mode][..., :3]))
    else:
        assert carla is None


@pytest.mark.filterwarnings("ignore::PIL.Image.DecompressionBombWarning")
@FUZZ
@given(
    width=st.integers(1, 2**31 - 1),
    height=st.integers(2, 2**31 - 1),  # more than the one pixel the data holds
    kind=st.sampled_from([(0, 8), (0, 16), (2, 8), (6, 16)]),
)
def test_headers_claiming_huge_images_fail_fast_without_decoding(
    workdir, width, height, kind
) -> None:
    """Decompression bombs and corrupt sizes: more than Image.MAX_IMAGE_PIXELS pixels is refused
    before anything is allocated; a large claim within the limit fails on the missing data."""
    colour_type, bits = kind
    pixels = np.zeros((1, 1, CHANNELS[colour_type]), np.uint16 if bits == 16 else np.uint8)
    data = encode_png(pixels[..., 0] if colour_type == 0 else pixels, bits, colour_type)
    # The header claims width x height; the IDAT holds one pixel.
    path = write_bytes(workdir / "huge.png", encode_png_header_only(data, width, height))
    for read in (read_rgb, read_depth_png, read_carla_depth):
        assert outcome(read, path) is None, read.__name__


def encode_png_header_only(data: bytes, width: int, height: int) -> bytes:
    """``data`` with IHDR's width and height replaced (checksum repaired)."""
    out = bytearray(data)
    out[16:24] = struct.pack(">II", width, height)
    return repair_png_crcs(bytes(out))


def test_a_header_within_the_pixel_limit_but_without_the_data_fails_quickly(workdir) -> None:
    data = encode_png(np.zeros((1, 1), np.uint8), 8, 0)
    path = write_bytes(workdir / "large.png", encode_png_header_only(data, 8000, 8000))
    for read in (read_rgb, read_depth_png, read_carla_depth):
        with time_limit(10):
            assert outcome(read, path) is None


# --- CARLA radar CSV --------------------------------------------------------------------------

any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)


@FUZZ
@given(rows=st.lists(st.tuples(any_float, any_float, any_float, any_float), max_size=12))
def test_radar_rows_with_nan_or_inf_are_dropped_and_negative_ranges_refused(workdir, rows) -> None:
    """The recorder's writer, any float values: the reader keeps exactly the all-finite rows in
    order, or refuses a negative range naming the file."""
    path = workdir / "radar.csv"
    recorder.write_radar([Detection(*row) for row in rows], path)
    kept = [row for row in rows if all(math.isfinite(v) for v in row)]
    values = outcome(read_radar_csv, path)
    if any(row[0] < 0 for row in kept):
        assert values is None
        return
    assert values is not None and values.dtype == np.float64 and values.shape == (len(kept), 4)
    np.testing.assert_array_equal(values, np.array(kept, dtype=np.float64).reshape(-1, 4))


JUNK_CELLS = ["nan", "NaN", "-inf", "Infinity", "1e999", "-1e999", "", " ", "abc", "0x1f"]
JUNK_CELLS += ["1,5", "1;5", "\x00", "1e-400", "--1", "1_0", '"3"', "१२"]


@st.composite
def radar_text(draw) -> bytes:
    """A radar CSV with junk in its cells, rows of the wrong length, blank lines, a byte order
    mark or CRLF endings, then maybe damaged bytes (truncated, invalid UTF-8)."""
    lines = [",".join(RADAR_COLUMNS)]
    if draw(st.booleans()):
        lines[0] = draw(st.sampled_from(["depth, azimuth, altitude, velocity", "x,y,z", ""]))
    cell = st.one_of(
        st.floats(-1e3, 1e3).map(repr),
        any_float.map(repr),
        st.sampled_from(JUNK_CELLS),
        st.text(max_size=6),
    )
    for _ in range(draw(st.integers(0, 8))):
        if draw(st.integers(0, 9)) == 0:
            lines.append("")
            continue
        lines.append(",".join(draw(st.lists(cell, min_size=3, max_size=5))))
    text = ("\r\n" if draw(st.booleans()) else "\n").join(lines)
    data = ("\ufeff" if draw(st.booleans()) else "").encode() + text.encode("utf-8", "replace")
    if data and draw(st.booleans()):
        data = draw(damaged(data))
    return data


@pytest.mark.slow
@FUZZ
@given(text=radar_text(), fov=st.floats(1.0, 179.0), yaw=st.floats(-180, 180))
def test_damaged_radar_files_load_finite_detections_or_fail_naming_the_file(
    workdir, text, fov, yaw
) -> None:
    path = write_bytes(workdir / "radar junk.csv", text)
    values = outcome(read_radar_csv, path)
    if values is None:
        return
    assert values.dtype == np.float64 and values.ndim == 2 and values.shape[1] == 4
    assert np.isfinite(values).all() and (values[:, 0] >= 0).all()
    # At most one detection per line after the header (csv ends lines at \n, \r or both).
    assert len(values) <= text.count(b"\n") + text.count(b"\r")
    pose = transform_matrix(
        {"location": {"x": 0.5, "y": 0, "z": -1}, "rotation": {"pitch": 0, "yaw": yaw, "roll": 0}}
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow or invalid-cast warnings either
        sparse = project_radar(values, pose, fov, (24, 32), (16, 32), max_range=250.0)
    assert sparse.dtype == np.float32 and sparse.shape == (16, 32)
    assert np.isfinite(sparse).all() and (sparse >= 0).all() and (sparse < 250.0).all()


@FUZZ
@given(
    detections=hnp.arrays(
        np.float64, st.tuples(st.integers(0, 20), st.just(4)), elements=any_float
    ),
    translation=st.tuples(*[st.floats(-1e300, 1e300)] * 3),
    rotation=st.tuples(*[st.floats(-1e6, 1e6)] * 3),
    max_range=st.one_of(st.just(math.inf), st.floats(1e-3, 250.0)),
)
# Found by this test in CI: x = cos²(2⁻²⁴) m is below 1 m in float64 but 1.0 in float32.
@example(
    detections=np.array([[1.0, 2.0**-24, 2.0**-24, 2.0**-24]]),
    translation=(0.0, 0.0, 0.0),
    rotation=(0.0, 0.0, 0.0),
    max_range=1.0,
)
def test_projected_radar_is_always_a_finite_sparse_map(
    detections, translation, rotation, max_range
) -> None:
    """Whatever finite pose and whatever detections (NaN, inf, 1e308): the sparse map a sample
    carries is finite, non-negative, below max_range, and computing it warns about nothing."""
    pose = transform_matrix(
        {
            "location": dict(zip("xyz", translation, strict=True)),
            "rotation": dict(zip(("pitch", "yaw", "roll"), rotation, strict=True)),
        }
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sparse = project_radar(detections, pose, 90.0, (32, 48), (32, 48), max_range)
    assert sparse.dtype == np.float32 and sparse.shape == (32, 48)
    assert np.isfinite(sparse).all() and (sparse >= 0).all()
    assert (sparse[sparse > 0] < max_range).all()


# --- CARLA frame metadata ----------------------------------------------------------------------

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**30), 10**30)
    | any_float
    | st.text(max_size=8)
    | st.sampled_from(["ClearNoon", "night", "Default"]),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3)
    ),
    max_leaves=8,
)


@st.composite
def meta_text(draw) -> tuple[bytes, dict | None]:
    """A frame's metadata as the recorder writes it, then one thing wrong (or nothing); returns
    the bytes and, when nothing is wrong, the dict they hold."""
    pose = {
        "location": {k: draw(st.floats(-5, 5)) for k in "xyz"},
        "rotation": {k: draw(st.floats(-180, 180)) for k in ("pitch", "yaw", "roll")},
    }
    meta = {
        "fov": draw(st.floats(1, 179)),
        "condition": draw(st.sampled_from(["ClearNoon", "HardRainNight", "FoggyNoon", "fog"])),
        "radar_to_camera": pose,
        "frame": 7,
    }
    how = draw(
        st.sampled_from(["none", "bytes", "value", "nested", "drop", "deep", "bigint", "nan"])
    )
    if how == "value":
        meta[draw(st.sampled_from(["fov", "condition", "radar_to_camera"]))] = draw(json_values)
    elif how == "nested":
        part = draw(st.sampled_from(["location", "rotation"]))
        key = draw(st.sampled_from(sorted(pose[part])))
        pose[part][key] = draw(json_values)
    elif how == "drop":
        del meta[draw(st.sampled_from(["fov", "condition", "radar_to_camera"]))]
    elif how == "nan":
        pose["rotation"]["yaw"] = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
    text = json.dumps(meta)  # allow_nan: Python writes NaN and Infinity
    if how == "deep":
        text = '{"fov": 90, "condition": "ClearNoon", "radar_to_camera": ' + "[" * 50_000
        text += "]" * 50_000 + "}"
    elif how == "bigint":
        text = text.replace(f'"fov": {json.dumps(meta["fov"])}', '"fov": ' + "9" * 5000, 1)
    data = text.encode()
    if how == "bytes":
        data = draw(damaged(data))
    return data, (meta if how == "none" else None)


@FUZZ
@given(case=meta_text())
def test_damaged_frame_metadata_loads_checked_or_fails_naming_the_file(workdir, case) -> None:
    data, meta = case
    path = write_bytes(workdir / "00000007.json", data)
    result = outcome(read_frame_meta, path)
    if meta is not None:
        assert result is not None and result.fov == meta["fov"]
        np.testing.assert_array_equal(
            result.radar_to_camera, transform_matrix(meta["radar_to_camera"])
        )
    if result is None:
        return
    assert 0 < result.fov < 180 and result.condition in CONDITIONS
    assert result.radar_to_camera.shape == (4, 4) and np.isfinite(result.radar_to_camera).all()


# --- Top-View NPY depth maps -------------------------------------------------------------------

NPY_DTYPES = [np.float16, np.float32, np.float64, np.int16, np.int64, np.uint8, np.uint16, ">f8"]
NPY_DTYPES += [np.bool_, np.complex64, "U3"]


@FUZZ
@given(
    array=hnp.arrays(
        st.sampled_from(NPY_DTYPES).map(np.dtype),
        hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=5),
    ),
    unit=st.sampled_from([1.0, 0.01, 1e300]),
    data=st.data(),
)
def test_npy_depth_maps_load_finite_or_fail_naming_the_file(workdir, array, unit, data) -> None:
    path = workdir / "depth.npy"
    np.save(path, array)
    original = path.read_bytes()
    if data.draw(st.booleans(), label="damage"):
        write_bytes(path, data.draw(damaged(original), label="damaged file"))
    depth = outcome(read_depth_file, path, unit)
    usable = array.dtype.kind in "fiu" and array.size > 0
    usable &= array.ndim == 2 or (array.ndim == 3 and array.shape[2] == 1)
    if path.read_bytes() == original:
        if not usable:
            assert depth is None
            return
        with np.errstate(over="ignore", invalid="ignore"):
            metres = array.reshape(array.shape[:2]).astype(np.float64) * unit
            valid = np.isfinite(metres) & (metres > 0) & (metres <= FLOAT32_MAX)
        np.testing.assert_array_equal(depth, np.where(valid, metres, 0).astype(np.float32))
    if depth is not None:
        assert depth.dtype == np.float32 and depth.ndim == 2
        assert np.isfinite(depth).all() and (depth >= 0).all()


def test_npy_files_that_are_not_depth_arrays_are_refused(workdir) -> None:
    # A header promising 10^10 float64 values over 16 bytes of data: refused without allocating.
    header = "{'descr': '<f8', 'fortran_order': False, 'shape': (100000, 100000), }"
    header += " " * (118 - len(header) - 1) + "\n"
    lying = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + bytes(16)
    np.savez(workdir / "archive.npz", depth=np.ones((2, 2)))
    cases = {
        "lying.npy": lying,
        "archive.npy": (workdir / "archive.npz").read_bytes(),
        "empty.npy": b"",
        "pickle.npy": None,
    }
    np.save(workdir / "pickle.npy", np.array([{"depth": 1}], dtype=object), allow_pickle=True)
    for name, content in cases.items():
        path = workdir / name
        if content is not None:
            path.write_bytes(content)
        with time_limit(10):
            assert outcome(read_depth_file, path, 1.0) is None, name


# --- the prepared cache ------------------------------------------------------------------------


def _frame(frame_id: str, size=(8, 12)) -> PreparedFrame:
    rng = np.random.default_rng(zlib.crc32(frame_id.encode()))
    return PreparedFrame(
        image=rng.integers(0, 256, (*size, 3), dtype=np.uint8),
        sparse=np.where(rng.random(size) < 0.2, rng.uniform(1, 80, size), 0.0),
        depth=rng.uniform(0.5, 80, size),
        condition="day",
    )


@pytest.fixture(scope="module")
def prepared_split(tmp_path_factory) -> Path:
    cache = tmp_path_factory.mktemp("prepared")
    return prepare_split(cache, "val", ["a", "b", "c"], _frame, {"test": True})


@FUZZ
@given(data=st.data())
def test_a_damaged_prepared_index_loads_or_fails_naming_it(prepared_split, data) -> None:
    index = prepared_split / "index.json"
    original = index.read_bytes()
    try:
        index.write_bytes(data.draw(damaged(original), label="damaged index"))
        try:
            with time_limit():
                split = PreparedSplit(prepared_split)
        except DataFileError as err:
            assert str(err).startswith(f"{index}: ") and err.path == index, str(err)
            return
        for i in range(len(split)):
            try:
                with time_limit():
                    sample = split[i]
            except (DataFileError, FileNotFoundError) as err:
                assert str(err).startswith(str(prepared_split)), str(err)
                continue
            assert sample["image"].shape[0] == 3
            assert (
                sample["sparse"].shape == sample["depth"].shape == (1, *sample["image"].shape[1:])
            )
            assert torch.isfinite(sample["sparse"]).all() and torch.isfinite(sample["depth"]).all()
    finally:
        index.write_bytes(original)


def test_a_damaged_frame_record_is_prepared_again(tmp_path) -> None:
    split_dir = prepare_split(tmp_path, "val", ["a", "b", "c"], _frame, {})
    (split_dir / "index.json").unlink()  # as after an interrupted prepare
    (split_dir / "000001.json").write_bytes(b'{"id": "b", "fi')
    made = []
    prepare_split(tmp_path, "val", ["a", "b", "c"], lambda i: made.append(i) or _frame(i), {})
    assert made == ["b"]
    assert [f["id"] for f in PreparedSplit(split_dir).frames] == ["a", "b", "c"]


# --- a real split through a DataLoader worker ----------------------------------------------------


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return record_fixture(tmp_path_factory.mktemp("carla") / "recording")


def _copy(recording: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(recording, tmp_path / "recording"))


def _carla(root: Path, tmp_path: Path, split: str = "train") -> CarlaDepth:
    return CarlaDepth(split, root, tmp_path / "cache", height=CARLA_H, width=CARLA_W)


def _loader(dataset) -> DataLoader:
    return DataLoader(dataset, batch_size=1, shuffle=False, num_workers=1, timeout=60)


def _drain(dataset) -> tuple[list[dict], Exception | None]:
    """Every batch a one-worker DataLoader yields before it raises, and what it raised. The
    error's traceback is dropped: its frames hold the loader's iterator, which would otherwise
    live (worker and all) until a later garbage collection shuts it down."""
    batches = []
    batch_iter = iter(_loader(dataset))
    try:
        for batch in batch_iter:
            batches.append(batch)
    except Exception as err:
        return batches, err.with_traceback(None)
    finally:
        del batch_iter  # shuts the worker down now
    return batches, None


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])


RAW_DAMAGE = {
    "truncated depth PNG": ("val/depth/00000210.png", _truncate),
    "16-bit RGB depth PNG": (
        "train/depth/00000120.png",
        lambda p: p.write_bytes(encode_png(np.full((CARLA_H, CARLA_W, 3), 700), 16, 2)),
    ),
    "16-bit grey camera image": (
        "test/rgb/00000310.png",
        lambda p: Image.fromarray(np.zeros((CARLA_H, CARLA_W), np.uint16)).save(p),
    ),
    "depth of another size": (
        "train/depth/00000130.png",
        lambda p: write_rgb_png(p, encode_carla_depth(np.full((CARLA_H, CARLA_W - 1), 9.0))),
    ),
    "radar junk": ("test/radar/00000300.csv", lambda p: p.write_text(p.read_text() + "1,2,x,4\n")),
    "radar negative range": (
        "val/radar/00000200.csv",
        lambda p: p.write_text(p.read_text() + "-3,0,0,0\n"),
    ),
    "metadata truncated": ("train/meta/00000110.json", _truncate),
}


@pytest.mark.parametrize("damage", list(RAW_DAMAGE))
def test_a_damaged_recording_fails_at_prepare_naming_the_file(recording, tmp_path, damage) -> None:
    name, apply = RAW_DAMAGE[damage]
    root = _copy(recording, tmp_path)
    apply(root / name)
    with pytest.raises(DataFileError) as info:
        _carla(root, tmp_path)
    assert str(info.value).startswith(f"{root / name}: ")
    assert info.value.path == root / name


def test_nan_radar_rows_never_reach_a_sample(recording, tmp_path) -> None:
    """NaN/inf detections are dropped: the frame's sparse map is the one without them, through a
    DataLoader worker."""
    root = _copy(recording, tmp_path)
    radar = root / "train/radar/00000110.csv"
    radar.write_text(
        radar.read_text()
        + "nan,0.1,0.0,1.0\n20.0,nan,0.0,1.0\ninf,0.0,0.0,0.0\n1e999,0,0,0\n5.0,0.0,0.0,nan\n"
    )
    clean, error = _drain(_carla(recording, tmp_path / "clean"))
    assert error is None
    dropped, error = _drain(_carla(root, tmp_path))
    assert error is None and len(dropped) == len(clean) == 4
    for got, want in zip(dropped, clean, strict=True):
        assert torch.isfinite(got["sparse"]).all()
        torch.testing.assert_close(got["sparse"], want["sparse"], rtol=0, atol=0)


CACHE_DAMAGE = {
    "truncated image": ("image", _truncate),
    "garbage sparse": ("sparse", lambda p: p.write_bytes(np.random.default_rng(0).bytes(500))),
    "float depth": ("depth", lambda p: np.save(p, np.zeros((CARLA_H, CARLA_W), np.float32))),
    "sparse of another size": (
        "sparse",
        lambda p: np.save(p, np.ones((CARLA_H - 1, CARLA_W), np.uint16)),
    ),
}


@pytest.mark.parametrize("damage", list(CACHE_DAMAGE))
def test_a_damaged_cached_frame_reaches_the_main_process_as_a_named_error(
    recording, tmp_path, damage
) -> None:
    """A worker reading a damaged cache file raises DataFileError; DataLoader re-raises it in the
    main process (same type, message naming the file) instead of dying or timing out."""
    which, apply = CACHE_DAMAGE[damage]
    train = _carla(recording, tmp_path)
    bad = train.split_dir / f"000002.{which}.npy"
    apply(bad)
    batches, error = _drain(train)
    assert len(batches) == 2  # the frames before the damaged one came through
    assert type(error) is DataFileError, repr(error)  # not a dead worker or a timeout
    message = str(error)
    assert f"{bad}: " in message and "DataLoader worker" in message


def test_a_damaged_topview_folder_fails_at_prepare_and_nan_depths_load_as_invalid(
    tmp_path_factory, tmp_path
) -> None:
    folder = write_folder(tmp_path_factory.mktemp("topview") / "data")
    depth = np.load(folder / "train/depth/a01.npy")
    depth[:4] = np.nan
    depth[4:8] = np.inf
    np.save(folder / "train/depth/a01.npy", depth)
    train = TopViewDepth("train", folder, tmp_path / "cache", height=64, width=96)
    batches, error = _drain(train)
    assert error is None and len(batches) == 4
    assert all(torch.isfinite(batch["depth"]).all() for batch in batches)
    assert (train[1]["depth"][0, :8] == 0).all() and (train[1]["depth"][0, 8:] > 0).all()
    _truncate(folder / "val/depth/b01.npy")
    with pytest.raises(DataFileError, match=f"^{re.escape(str(folder))}/val/depth/b01.npy: unr"):
        TopViewDepth("train", folder, tmp_path / "cache2", height=64, width=96)
