"""The C API of include/pillarseg/pillarseg.h through ctypes: where the shared library is found,
the layout of pillarseg_options, and each function's argument and result types.

The library is looked for, in this order, at
  1. $PILLARSEG_LIBRARY (a path to libpillarseg.so.*; when set, nothing else is tried),
  2. the library `cmake --install` put beside this package (its path relative to the package
     is written into _installed.py at install time),
  3. ctypes.util.find_library("pillarseg") (ldconfig's cache, LD_LIBRARY_PATH).
"""

import ctypes
import ctypes.util
import os
from pathlib import Path

NUM_CLASSES = 12
ERROR_SIZE = 1024


class Options(ctypes.Structure):
    """pillarseg_options, field for field (a later library reads only the fields this size holds)."""

    _fields_ = [
        ("struct_size", ctypes.c_size_t),
        ("device", ctypes.c_char_p),
        ("threads", ctypes.c_int),
        ("cuda_device", ctypes.c_int),
        ("mask_unobserved", ctypes.c_int),
        ("convolution", ctypes.c_char_p),
        ("precision", ctypes.c_char_p),
        ("reflectance_none", ctypes.c_int),
        ("reflectance_scale", ctypes.c_float),
        ("reflectance_offset", ctypes.c_float),
        ("reflectance_clip", ctypes.c_int),
        ("transform", ctypes.c_double * 16),
        ("flips", ctypes.c_int),
    ]


# name: (result type, argument types)
_SIGNATURES = {
    "pillarseg_version": (ctypes.c_char_p, []),
    "pillarseg_init_options": (None, [ctypes.POINTER(Options), ctypes.c_size_t]),
    "pillarseg_open": (ctypes.c_void_p, [ctypes.c_char_p, ctypes.c_char_p, ctypes.POINTER(Options),
                                         ctypes.c_char_p, ctypes.c_size_t]),
    "pillarseg_grid": (None, [ctypes.c_void_p, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int)]),
    "pillarseg_grid_geometry": (None, [ctypes.c_void_p, ctypes.POINTER(ctypes.c_double),
                                       ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_double)]),
    "pillarseg_device_name": (ctypes.c_char_p, [ctypes.c_void_p]),
    "pillarseg_precision": (ctypes.c_char_p, [ctypes.c_void_p]),
    "pillarseg_class_name": (ctypes.c_char_p, [ctypes.c_int]),
    "pillarseg_segment": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p,
                                         ctypes.c_void_p, ctypes.c_char_p, ctypes.c_size_t]),
    "pillarseg_close": (None, [ctypes.c_void_p]),
    "pillarseg_read_points": (ctypes.c_int, [ctypes.c_char_p, ctypes.c_char_p,
                                             ctypes.POINTER(ctypes.POINTER(ctypes.c_float)),
                                             ctypes.POINTER(ctypes.c_size_t), ctypes.c_char_p, ctypes.c_size_t]),
    "pillarseg_free": (None, [ctypes.c_void_p]),
}


def _candidates():
    """[(path or name, where it came from)] in the order they are tried."""
    explicit = os.environ.get("PILLARSEG_LIBRARY")
    if explicit:
        return [(explicit, "$PILLARSEG_LIBRARY")]
    found = []
    try:
        from . import _installed
    except ImportError:
        found.append((None, "beside the package (not installed by cmake --install: no _installed.py)"))
    else:
        found.append((str(Path(__file__).resolve().parent / _installed.LIBRARY), "beside the package"))
    found.append((ctypes.util.find_library("pillarseg"), 'ctypes.util.find_library("pillarseg")'))
    return found


def _load():
    tried = []
    for path, origin in _candidates():
        if path is None:
            tried.append(f"{origin}: none")
            continue
        try:
            library = ctypes.CDLL(path)
        except OSError as e:
            tried.append(f"{origin}: {e}")
            continue
        for name, (restype, argtypes) in _SIGNATURES.items():
            try:
                function = getattr(library, name)
            except AttributeError:
                raise ImportError(f"pillarseg: {path} ({origin}) has no {name}: it is not libpillarseg, or one "
                                  f"older than this module") from None
            function.restype = restype
            function.argtypes = argtypes
        return library, path
    raise ImportError("pillarseg: no libpillarseg could be loaded (set PILLARSEG_LIBRARY to its path); tried\n  "
                      + "\n  ".join(tried))


lib, library_path = _load()


def default_options():
    """The library's defaults in an Options of this module's size (pillarseg_init_options writes
    no more than the size it is given; a newer library's longer struct is cut to this one)."""
    options = Options()
    lib.pillarseg_init_options(ctypes.byref(options), ctypes.sizeof(Options))
    options.struct_size = ctypes.sizeof(Options)
    return options


def error_buffer():
    return ctypes.create_string_buffer(ERROR_SIZE)


def message(buffer):
    return buffer.value.decode("utf-8", errors="replace")
