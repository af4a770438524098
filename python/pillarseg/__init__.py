"""pillarseg: a dense top-view semantic grid map from one LiDAR sweep (PillarSegNet), in Python.

    import pillarseg
    points = pillarseg.read_points("000000.bin")            # (N, 4) float32: x, y, z, reflectance
    with pillarseg.Segmenter("model.safetensors") as segmenter:
        labels = segmenter.segment(points)                    # (H, W) uint8 class ids
        labels, probs = segmenter.segment(points, probabilities=True)   # probs: (12, H, W) float32
    print(pillarseg.class_names[labels[0, 0]])

A thin layer over the C API (include/pillarseg/pillarseg.h) through ctypes: numpy arrays go in
and come out, the library's errors are raised as pillarseg.Error with its message. See
docs/python.md for how the library is found.
"""

import ctypes
import os
import threading
from collections import namedtuple

import numpy as np

from . import _capi

__all__ = ["Error", "Segmenter", "Geometry", "read_points", "as_points", "class_names", "NUM_CLASSES",
           "library_version", "library_path"]

__version__ = "0.5.0"

NUM_CLASSES = _capi.NUM_CLASSES
# class_names[k]: the name of class id k ("unlabeled" for 0, then "vehicle" ... "terrain").
class_names = tuple(_capi.lib.pillarseg_class_name(k).decode() for k in range(NUM_CLASSES + 1))
# The library's own version ("0.5.0") and the file it was loaded from.
library_version = _capi.lib.pillarseg_version().decode()
library_path = _capi.library_path

Geometry = namedtuple("Geometry", ["x_min", "y_min", "cell"])
Geometry.__doc__ = ("The map's placement: cell (ix, iy), i.e. labels[iy, ix], covers x in "
                    "[x_min + ix cell, x_min + (ix + 1) cell) and likewise y, metres in the model's frame.")


class Error(RuntimeError):
    """An error the library reported (its message names the function, the file or the argument)."""


def _encode(text, name):
    if not isinstance(text, str):
        raise TypeError(f"{name} must be a str, got {type(text).__name__}")
    return text.encode()


def as_points(points):
    """The (N, 4) float32 C-contiguous array of x, y, z, reflectance that segment() hands the library.

    `points` itself when it already is one (no copy: the library reads the caller's memory);
    otherwise one conversion into a new array: another dtype (float64, integers), another byte
    order or layout (a slice, a transposed or Fortran-ordered array), or (N, 3) points, which get
    reflectance 0."""
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] not in (3, 4):
        raise ValueError(f"points: expected an (N, 4) array of x, y, z, reflectance or an (N, 3) array of "
                         f"x, y, z, got shape {array.shape}")
    if array.dtype.kind not in "fiu":
        raise TypeError(f"points: expected real numbers, got dtype {array.dtype}")
    if (array.shape[1] == 4 and array.dtype == np.dtype(np.float32) and array.flags.c_contiguous
            and array.flags.aligned):
        return array
    converted = np.zeros((array.shape[0], 4), dtype=np.float32)
    converted[:, :array.shape[1]] = array
    return converted


def read_points(path, format=None):
    """The points of a LiDAR file as an (N, 4) float32 array (x, y, z, reflectance), read by the library.

    format: None (by the file's extension: .bin, .pcd, .ply, .npy, .pcd.bin) or "kitti", "pcd",
    "ply", "npy", "nuscenes". The values are as stored (no input settings apply); points with a
    non-finite value are left out. The library's buffer is copied once into the returned array
    and freed."""
    buffer = ctypes.POINTER(ctypes.c_float)()
    count = ctypes.c_size_t(0)
    error = _capi.error_buffer()
    format_name = None if format is None else _encode(format, "format")
    status = _capi.lib.pillarseg_read_points(os.fsencode(path), format_name, ctypes.byref(buffer),
                                             ctypes.byref(count), error, _capi.ERROR_SIZE)
    try:
        if status != 0:
            raise Error(_capi.message(error))
        if count.value == 0:
            return np.zeros((0, 4), dtype=np.float32)
        return np.ctypeslib.as_array(buffer, shape=(count.value, 4)).copy()
    finally:
        _capi.lib.pillarseg_free(buffer)


class Segmenter:
    """A PillarSegNet model open on a device: segment(points) -> the (H, W) label map.

    weights: a safetensors checkpoint (one `pillarseg train` wrote, or weights only).
    config: a run config YAML whose grid:, model: and input: settings win over the checkpoint's.
    device: "cpu", "cuda" (a GPU) or "emu" (the CUDA backend on the CPU emulation: slow).
    precision: the convolutions' arithmetic, "fp32", "bf16", "fp16" or "int8" (weights calibrated by
        `pillarseg calibrate`; see the `precision` property).
    threads: CPU threads (0: all). cuda_device: the GPU ordinal with "cuda".
    mask_unobserved: cells no ray observed get class 0 and probabilities 0.
    convolution: with "cuda", "own", "cudnn" or "cublas".
    reflectance: how the sensor's reflectance maps to the model's [0, 1]: None (as stored, or as
        the config's input: section says), "none" (the sensor has none: every point gets 0), or a
        dict with any of scale (default 1), offset (0), clip (True): reflectance = scale * r +
        offset, clamped to [0, 1] when clip is true.
    transform: a 4 x 4 matrix (nested lists or an array) taking the sensor's frame into the
        model's (sensor at the origin, x forward, z up); None or the identity: the points' own
        frame (or the config's input: transform).
    flips: test-time mirrors, 1 (the scan alone), 2 (and its mirror y -> -y) or 4 (and x -> -x,
        and both): the probabilities are the mean over the copies, each a pass of the network
        (flips times the work); the grid must be symmetric about the sensor.

    One call at a time: calls from several threads are serialised. Use it as a context manager or
    call close(); a closed segmenter raises Error."""

    def __init__(self, weights, config=None, device="cpu", precision="fp32", threads=0, *, cuda_device=0,
                 mask_unobserved=False, convolution="own", reflectance=None, transform=None, flips=1):
        options = _capi.default_options()
        options.device = _encode(device, "device")
        options.precision = _encode(precision, "precision")
        options.convolution = _encode(convolution, "convolution")
        options.threads = _integer(threads, "threads")
        options.cuda_device = _integer(cuda_device, "cuda_device")
        options.mask_unobserved = 1 if mask_unobserved else 0
        options.flips = _integer(flips, "flips")
        _set_reflectance(options, reflectance)
        if transform is not None:
            options.transform[:] = _transform(transform)
        self._weights = os.fspath(weights)
        self._lock = threading.Lock()
        error = _capi.error_buffer()
        self._handle = _capi.lib.pillarseg_open(os.fsencode(weights),
                                                None if config is None else os.fsencode(config),
                                                ctypes.byref(options), error, _capi.ERROR_SIZE)
        if not self._handle:
            raise Error(_capi.message(error))
        width, height = ctypes.c_int(), ctypes.c_int()
        _capi.lib.pillarseg_grid(self._handle, ctypes.byref(width), ctypes.byref(height))
        self._grid = (height.value, width.value)

    def _open_handle(self):
        if not self._handle:
            raise Error(f"the segmenter of {self._weights} is closed")
        return self._handle

    @property
    def grid(self):
        """The label map's shape: (height, width), rows along y and columns along x."""
        self._open_handle()
        return self._grid

    @property
    def geometry(self):
        """Geometry(x_min, y_min, cell): where the map's cells lie, metres."""
        x_min, y_min, cell = (ctypes.c_double() for _ in range(3))
        _capi.lib.pillarseg_grid_geometry(self._open_handle(), ctypes.byref(x_min),
                                          ctypes.byref(y_min), ctypes.byref(cell))
        return Geometry(x_min.value, y_min.value, cell.value)

    @property
    def device_name(self):
        """The device it runs on, e.g. "cpu" or "cuda:0 (NVIDIA H200)"."""
        return _capi.lib.pillarseg_device_name(self._open_handle()).decode()

    @property
    def precision(self):
        """The convolutions' arithmetic: "fp32", "bf16" or "fp16" (fp32 where the device has no 16-bit path)."""
        return _capi.lib.pillarseg_precision(self._open_handle()).decode()

    def segment(self, points, probabilities=False):
        """Segments one sweep: labels, or (labels, probabilities) with probabilities=True.

        points: (N, 4) x, y, z, reflectance in the sensor's frame (metres), or (N, 3) with
        reflectance 0; any N, including 0; points with a non-finite value are ignored. An (N, 4)
        float32 C-contiguous array is read in place; anything else is converted once (as_points).
        labels: (H, W) uint8 class ids 1..12 (0: unobserved, with mask_unobserved).
        probabilities: (12, H, W) float32 softmax, class k in plane k - 1.
        Both are new arrays the library fills directly."""
        array = as_points(points)
        height, width = self.grid
        labels = np.empty((height, width), dtype=np.uint8)
        probs = np.empty((NUM_CLASSES, height, width), dtype=np.float32) if probabilities else None
        error = _capi.error_buffer()
        with self._lock:
            status = _capi.lib.pillarseg_segment(self._open_handle(), array.ctypes.data, array.shape[0],
                                                 labels.ctypes.data, None if probs is None else probs.ctypes.data,
                                                 error, _capi.ERROR_SIZE)
        if status != 0:
            raise Error(_capi.message(error))
        return (labels, probs) if probabilities else labels

    def close(self):
        """Frees the model and its device memory; closing twice is harmless."""
        with self._lock:
            handle, self._handle = self._handle, None
            _capi.lib.pillarseg_close(handle)

    @property
    def closed(self):
        return not self._handle

    def __enter__(self):
        self._open_handle()
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        if getattr(self, "_handle", None):
            self.close()

    def __repr__(self):
        if not self._handle:
            return f"<pillarseg.Segmenter {self._weights!r} (closed)>"
        height, width = self._grid
        return (f"<pillarseg.Segmenter {self._weights!r} on {self.device_name}, {self.precision}, "
                f"{height} x {width} cells>")


def _integer(value, name):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an int, got {value!r}")
    return int(value)


def _set_reflectance(options, reflectance):
    expected = 'reflectance: expected None, "none" or a dict of scale, offset, clip'
    if reflectance is None:
        return
    if isinstance(reflectance, str):
        if reflectance != "none":
            raise ValueError(f"{expected}, got {reflectance!r}")
        options.reflectance_none = 1
        return
    if not isinstance(reflectance, dict):
        raise TypeError(f"{expected}, got {reflectance!r}")
    unknown = set(reflectance) - {"scale", "offset", "clip"}
    if unknown:
        raise ValueError(f"reflectance: unknown keys {sorted(unknown)} (expected scale, offset, clip)")
    if "scale" in reflectance:
        options.reflectance_scale = float(reflectance["scale"])
    if "offset" in reflectance:
        options.reflectance_offset = float(reflectance["offset"])
    if "clip" in reflectance:
        options.reflectance_clip = 1 if reflectance["clip"] else 0


def _transform(transform):
    """The 16 row-major values of a 4 x 4 matrix."""
    matrix = np.asarray(transform, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise ValueError(f"transform: expected a 4 x 4 matrix, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise ValueError("transform: every entry must be finite")
    return matrix.ravel().tolist()
