"""Reading and writing the image and depth files every dataset shares.

Depth maps on disk follow KITTI's convention: uint16 holding metres × 256 (3.9 mm steps, up to
:data:`MAX_ENCODED_DEPTH` = 255.996 m), 0 meaning "no measurement": single-channel 16-bit PNGs
(a dataset's own files) or uncompressed ``.npy`` arrays (the prepared caches,
:func:`write_npy`/:func:`read_npy`, which decode about 40 times faster). Every reader raises an
error that names the file and what was expected, so a corrupt frame is never turned into a black
image; every writer goes through a temporary sibling and a rename, so a reader never sees half a
file.

Bad files. A missing file raises :class:`FileNotFoundError`; a file that exists but cannot be
used (truncated, corrupt, the wrong format, bit depth or size, or an image whose header claims
more than ``PIL.Image.MAX_IMAGE_PIXELS`` pixels, Pillow's decompression-bomb limit) raises
:class:`DataFileError`, whatever the decoder underneath raised. Both messages start with the path.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from fusion_depth.utils.atomic import write_atomic

DEPTH_PNG_SCALE = 256.0  # stored uint16 = round(metres × DEPTH_PNG_SCALE), 0 = no value
_UINT16_MAX = np.iinfo(np.uint16).max
# The farthest depth uint16 × 1/256 m holds (255.996 m): a prepared cache refuses a frame beyond.
MAX_ENCODED_DEPTH = _UINT16_MAX / DEPTH_PNG_SCALE
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Modes Pillow converts to RGB exactly: 8-bit grey, palette, colour, with or without alpha
# (alpha is dropped, not composited), bilevel, CMYK/YCbCr JPEGs. Not 16/32-bit single channel
# ("I;16", "I", "F"): Pillow clips those to 0..255, and in a depth dataset such a file is a depth
# map in the image folder, not a photo.
_RGB_MODES = frozenset(
    {"1", "L", "LA", "La", "P", "PA", "RGB", "RGBA", "RGBa", "RGBX", "CMYK", "YCbCr"}
)
_DEPTH_MODES = frozenset({"I", "I;16", "I;16B", "I;16L"})


class DataFileError(ValueError):
    """A data file that exists but cannot be used: truncated, corrupt, or not what the reader
    expects (format, bit depth, size, values). The message starts with the file's path and says
    what was expected; ``path`` holds it. A ValueError, so code catching bad input keeps working.

    ``DataFileError(path, problem)`` builds the message ``"<path>: <problem>"``;
    ``DataFileError(message)`` takes a finished one (how pickling and DataLoader workers, which
    re-raise a worker's error in the main process, rebuild it).
    """

    def __init__(self, path: str | os.PathLike, problem: str | None = None) -> None:
        if problem is None:
            self.path, self.problem = None, None
            super().__init__(str(path))
        else:
            self.path, self.problem = Path(path), problem
            super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        if self.path is None:
            return type(self), (str(self),)
        return type(self), (self.path, self.problem)


def open_image(path: str | os.PathLike, what: str, verify: bool = True) -> Image.Image:
    """The decoded image, or FileNotFoundError / DataFileError naming ``path``.

    Decoding happens here, so a truncated file fails now and not later in a worker. Anything the
    decoder raises for the file's bytes (OSError, SyntaxError, struct.error, zlib errors, ...)
    becomes a DataFileError; so does a header claiming more than ``Image.MAX_IMAGE_PIXELS``
    pixels, checked before anything is decoded or allocated.

    ``verify`` also inflates a PNG's image data a second time to check it fills the image its
    header declares: Pillow stops at the end of the compressed stream and leaves the rows after
    it black (zeros), so a PNG whose data ends early (a damaged or hand-made file; plain
    truncation and garbled bytes are caught anyway) would load as a partly black image. It costs
    about as much again as the decode, so the prepared cache, whose files the platform wrote
    itself, reads with ``verify=False``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing {what}")
    try:
        image = Image.open(path)
    except Exception as err:  # any decoder error is about the file's bytes
        raise DataFileError(path, f"unreadable {what} ({type(err).__name__}: {err})") from err
    try:
        width, height = image.size
        limit = Image.MAX_IMAGE_PIXELS
        if limit is not None and width * height > limit:
            raise DataFileError(
                path,
                f"{what} of {width}x{height} pixels, more than PIL.Image.MAX_IMAGE_PIXELS="
                f"{limit} (a corrupt header or a decompression bomb; raise the limit if the "
                "image really is that large)",
            )
        if width < 1 or height < 1:
            raise DataFileError(path, f"{what} of {width}x{height} pixels, expected a real image")
        image.load()
        problem = _png_data_problem(path) if verify and image.format == "PNG" else None
        if problem:
            raise DataFileError(path, f"{what} whose {problem}")
    except DataFileError:
        image.close()
        raise
    except Exception as err:
        image.close()
        raise DataFileError(path, f"unreadable {what} ({type(err).__name__}: {err})") from err
    return image


_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # colour type: grey, RGB, palette, grey+A, RGBA
_ADAM7 = ((0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2))
_ADAM7 += ((0, 1, 1, 2),)  # (x0, y0, dx, dy) of the 7 interlace passes


def _png_data_problem(path: Path) -> str | None:
    """Why a PNG's image data (its IDAT chunks, inflated) is shorter than the image its header
    declares needs, or None when it is long enough (PNG specification, sections 7-8)."""
    data = path.read_bytes()
    if data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR" or len(data) < 29:
        return None
    width, height, bits, colour, _, _, interlace = struct.unpack(">IIBBBBB", data[16:29])
    if colour not in _PNG_CHANNELS:
        return None
    passes = [(0, 0, 1, 1)] if interlace == 0 else _ADAM7
    needed = 0
    for x0, y0, dx, dy in passes:
        rows, cols = (height - y0 + dy - 1) // dy, (width - x0 + dx - 1) // dx
        if rows > 0 and cols > 0:  # each row: a filter byte and the packed samples
            needed += rows * (1 + (cols * _PNG_CHANNELS[colour] * bits + 7) // 8)
    inflate = zlib.decompressobj()
    got, pos = 0, 8
    while pos + 8 <= len(data) and got < needed:
        length, kind = struct.unpack(">I4s", data[pos : pos + 8])
        if kind == b"IDAT":  # at most what is still needed: a bomb inflates no further
            got += len(inflate.decompress(data[pos + 8 : pos + 8 + length], needed - got))
        pos += 12 + length
    if got < needed:
        return f"image data ends after {got} of the {needed} bytes a {width}x{height} image needs"
    return None


def png_bit_depth(path: str | os.PathLike) -> int | None:
    """Bits per channel of a PNG from its IHDR chunk (1, 2, 4, 8 or 16); None if ``path`` is not
    a PNG. Pillow opens 16-bit colour PNGs as 8-bit "RGB", so this is how a reader tells them
    apart."""
    with open(path, "rb") as f:
        head = f.read(26)
    if len(head) < 26 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    return head[24]


def read_rgb(path: str | os.PathLike, verify: bool = True) -> np.ndarray:
    """An image file as uint8 (H, W, 3) RGB.

    8-bit colour, grey (replicated), palette and bilevel images are converted exactly; alpha is
    dropped; a 16-bit colour PNG keeps the high byte of each value. A 16/32-bit single-channel
    or float image (a depth map?) raises DataFileError, as does anything unreadable.
    ``verify``: see :func:`open_image`.
    """
    image = open_image(path, "image", verify)
    if image.mode not in _RGB_MODES:
        raise DataFileError(
            path,
            f"an image of mode {image.mode!r}, expected an 8-bit colour or grey image (RGB, "
            "RGBA, L, LA, P, 1); a 16-bit single-channel file is a depth map, not a camera image",
        )
    try:
        return np.asarray(image.convert("RGB"))
    except Exception as err:  # e.g. a palette image whose palette is broken
        raise DataFileError(
            path, f"an image of mode {image.mode!r} that does not convert to RGB ({err})"
        ) from err


def read_depth_png(
    path: str | os.PathLike, scale: float = DEPTH_PNG_SCALE, verify: bool = True
) -> np.ndarray:
    """A uint16 depth PNG as float32 (H, W) metres (``value / scale``; 0 stays 0 = invalid).

    Anything but a single-channel 16-bit image (8-bit grey, colour, palette, alpha, bilevel)
    raises DataFileError: there is no exact conversion to metres from those. ``verify``: see
    :func:`open_image`.
    """
    image = open_image(path, "depth PNG", verify)
    array = np.asarray(image)
    if array.ndim != 2 or array.dtype.kind not in "iu" or image.mode not in _DEPTH_MODES:
        raise DataFileError(
            path,
            f"expected a single-channel 16-bit depth PNG, got mode {image.mode!r} with shape "
            f"{array.shape}",
        )
    if array.size and (int(array.min()) < 0 or int(array.max()) > _UINT16_MAX):
        raise DataFileError(
            path,
            f"values {int(array.min())}..{int(array.max())}, expected a 16-bit depth image "
            f"(0..{_UINT16_MAX})",
        )
    return (array.astype(np.float32) / scale).astype(np.float32)


def encode_depth(depth: np.ndarray, scale: float = DEPTH_PNG_SCALE) -> np.ndarray:
    """Metres to uint16 ``round(depth * scale)``; non-finite or negative values become 0, values
    beyond ``65535 / scale`` m are clipped to 65535 (:func:`depth_beyond_encoding` finds them
    first where that must not happen silently)."""
    depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    return np.clip(np.round(depth * scale), 0, _UINT16_MAX).astype(np.uint16)


def depth_beyond_encoding(depth: np.ndarray, scale: float = DEPTH_PNG_SCALE) -> float | None:
    """The largest finite depth (metres) of ``depth`` that uint16 ``round(depth * scale)``
    cannot hold (it would round above 65535, i.e. beyond :data:`MAX_ENCODED_DEPTH` at the
    default scale), or None when every value fits. Non-finite and negative values are not
    counted: :func:`encode_depth` makes them 0 (no value)."""
    depth = np.asarray(depth)
    finite = depth[np.isfinite(depth)]
    if not finite.size:
        return None
    largest = float(finite.max())
    return largest if np.round(largest * scale) > _UINT16_MAX else None


def _save_atomic(image: Image.Image, path: Path) -> None:
    write_atomic(path, lambda tmp: image.save(tmp, format="PNG"))


def write_depth_png(
    path: str | os.PathLike, depth: np.ndarray, scale: float = DEPTH_PNG_SCALE
) -> None:
    """Float (H, W) metres to a uint16 PNG, written atomically."""
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"{path}: expected a (H, W) depth map, got shape {depth.shape}")
    _save_atomic(Image.fromarray(encode_depth(depth, scale)), Path(path))


def short_reason(err: BaseException, limit: int = 80) -> str:
    """``Type: first line of the message``, cut to ``limit`` characters: what numpy said about
    a bad file, without the bytes it may quote."""
    lines = str(err).strip().splitlines()
    text = f"{type(err).__name__}: {lines[0]}" if lines else type(err).__name__
    return text if len(text) <= limit else text[: limit - 1] + "…"


def write_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    """``array`` as an uncompressed ``.npy`` file (C order, no pickle), written atomically (a
    temporary sibling, then a rename): any numpy reads it with ``np.load``."""
    array = np.ascontiguousarray(array)

    def save(tmp: Path) -> None:
        with tmp.open("wb") as f:
            np.save(f, array, allow_pickle=False)

    write_atomic(Path(path), save, suffix=".npy")


def read_npy(
    path: str | os.PathLike,
    dtype: np.dtype | type,
    shape: tuple[int | None, ...],
    what: str,
    hint: str = "",
) -> np.ndarray:
    """An ``.npy`` file as :func:`write_npy` saved it, checked before its data is read.

    Args:
        dtype: the dtype the file must hold (byte order included: numpy's native one).
        shape: the shape it must have; ``None`` for a length that may be anything.
        what: the file's role, for messages (``"prepared image"``).
        hint: appended to every DataFileError (what to do, e.g. delete the cache folder).

    Returns:
        A fresh, writable C-order array of ``dtype`` and ``shape``.

    Raises:
        FileNotFoundError: there is no file at ``path``.
        DataFileError: naming ``path``: not an ``.npy`` file (an ``.npz`` archive, garbage), a
            Fortran-order, pickled or other-dtype array, another shape, or a file whose size
            is not what its header promises (truncated, or a header claiming more than the file
            holds: nothing is allocated for it).
    """
    return _npy(path, dtype, shape, what, hint, read=True)


def check_npy(
    path: str | os.PathLike,
    dtype: np.dtype | type,
    shape: tuple[int | None, ...],
    what: str,
    hint: str = "",
) -> tuple[int, ...]:
    """The shape of the ``.npy`` file at ``path``, checked as :func:`read_npy` checks it (header,
    dtype, shape, size) without reading its data. Raises as :func:`read_npy`."""
    return _npy(path, dtype, shape, what, hint, read=False)


def _npy(
    path: str | os.PathLike,
    dtype: np.dtype | type,
    shape: tuple[int | None, ...],
    what: str,
    hint: str,
    read: bool,
) -> Any:
    path = Path(path)
    dtype = np.dtype(dtype)
    expected = f"{dtype} ({', '.join('N' if n is None else str(n) for n in shape)})"
    tail = f"; {hint}" if hint else ""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing {what}")
    try:
        with path.open("rb") as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                got_shape, fortran, got_dtype = np.lib.format.read_array_header_1_0(f)
            else:
                got_shape, fortran, got_dtype = np.lib.format.read_array_header_2_0(f)
            fits = len(got_shape) == len(shape) and all(
                n is None or n == g for n, g in zip(shape, got_shape, strict=True)
            )
            if got_dtype != dtype or fortran or not fits:
                order = " in Fortran order" if fortran else ""
                raise DataFileError(
                    path, f"{what} of {got_dtype} {got_shape}{order}, expected {expected}{tail}"
                )
            count = int(np.prod(got_shape, dtype=np.int64))
            size = os.fstat(f.fileno()).st_size - f.tell()
            if size != count * dtype.itemsize:
                raise DataFileError(
                    path,
                    f"{what} of {size} data bytes, its header promises {dtype} {got_shape} "
                    f"({count * dtype.itemsize} bytes): truncated or damaged{tail}",
                )
            if not read:
                return tuple(got_shape)
            array = np.fromfile(f, dtype=dtype, count=count)
    except DataFileError:
        raise
    except Exception as err:  # numpy raises ValueError, OSError, EOFError, ... for bad bytes
        raise DataFileError(
            path, f"unreadable {what} ({short_reason(err)}), expected {expected}{tail}"
        ) from err
    if array.size != count:  # the file shrank while it was read
        raise DataFileError(path, f"{what} ended early, expected {expected}{tail}")
    return array.reshape(got_shape)


def write_rgb_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """uint8 (H, W, 3) to an RGB PNG, written atomically."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(
            f"{path}: expected a uint8 (H, W, 3) image, got {image.dtype} {image.shape}"
        )
    _save_atomic(Image.fromarray(image, "RGB"), Path(path))
