#!/usr/bin/env python3
"""Writes the seed corpora of the fuzz targets, fuzz/corpus/<reader>/: small valid and near-valid
inputs of every format, built here from the formats' definitions (engine/data/semantickitti.hpp,
engine/data/point_formats.hpp, engine/data/cache.hpp, weights_io/safetensors.hpp, the C API
targets' input layouts). With
--pillarseg BIN it also simulates two scans and trains the tiny model (fuzz/tiny_model.yaml) one
epoch with a ground-truth cache, and adds what that wrote: a crop of a simulated scan, its labels,
poses.txt and calib.txt, cache entries (their key set to the cache_entry target's) and the trained
checkpoint, with and without its metadata. Deterministic: the same inputs give the same files.

Usage: fuzz/make_seeds.py [--pillarseg build/pillarseg] [--out fuzz/corpus]
"""

import argparse
import json
import math
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

FUZZ_DIR = Path(__file__).resolve().parent
ROOT = FUZZ_DIR.parent
sys.path.insert(0, str(ROOT / "tests" / "support"))
from run_logs import masked_crc32c  # noqa: E402 (TFRecord's CRC, shared with the fault tests)

# The key of fuzz/cache_entry_fuzz.cpp (CacheKey::text()).
CACHE_KEY = (b"sequence=/fuzz/sequences/00\nframe=0\nkind=gt-sparse\n"
             b"settings=0123456789abcdef\ninputs=fedcba9876543210\n")
CACHE_DTYPES = {"u8": 1, "u16": 2, "u32": 3, "i32": 4, "i64": 5, "f32": 6, "f64": 7, "bytes": 8}


def fnv1a64(data):
    h = 0xcbf29ce484222325
    for b in data:
        h = ((h ^ b) * 0x100000001b3) & 0xFFFFFFFFFFFFFFFF
    return h


def points_bytes(points):
    return b"".join(struct.pack("<4f", *p) for p in points)


def cache_entry(dtype, shape, payload, key=CACHE_KEY, checksum=None):
    out = b"PSCACHE1" + struct.pack("<II", 1, len(key)) + key
    out += struct.pack("<II", CACHE_DTYPES[dtype], len(shape))
    out += b"".join(struct.pack("<q", d) for d in shape)
    out += struct.pack("<QQ", len(payload), fnv1a64(payload) if checksum is None else checksum)
    return out + payload


def parse_cache_entry(data):
    """(key, everything after the key) of a cache file, checking its payload checksum."""
    assert data[:8] == b"PSCACHE1", "not a cache entry"
    version, key_bytes = struct.unpack_from("<II", data, 8)
    assert version == 1
    key = data[16:16 + key_bytes]
    rest = data[16 + key_bytes:]
    _, rank = struct.unpack_from("<II", rest, 0)
    payload_bytes, checksum = struct.unpack_from("<QQ", rest, 8 + 8 * rank)
    payload = rest[8 + 8 * rank + 16:]
    assert len(payload) == payload_bytes and fnv1a64(payload) == checksum, "checksum mismatch"
    return key, rest


def safetensors(tensors, metadata=None, pad=True):
    """tensors: name -> (dtype, shape, bytes), laid out in the given order."""
    header, data = {}, b""
    if metadata:
        header["__metadata__"] = metadata
    for name, (dtype, shape, raw) in tensors.items():
        header[name] = {"dtype": dtype, "shape": shape, "data_offsets": [len(data), len(data) + len(raw)]}
        data += raw
    text = json.dumps(header, separators=(",", ":")).encode()
    if pad:
        text += b" " * ((8 - (8 + len(text)) % 8) % 8)
    return struct.pack("<Q", len(text)) + text + data


def read_safetensors(data):
    (n,) = struct.unpack_from("<Q", data, 0)
    header = json.loads(data[8:8 + n])
    buffer = data[8 + n:]
    metadata = header.pop("__metadata__", {})
    tensors = {}
    for name, e in sorted(header.items(), key=lambda kv: kv[1]["data_offsets"]):
        b, end = e["data_offsets"]
        tensors[name] = (e["dtype"], e["shape"], buffer[b:end])
    return tensors, metadata


def f32(*values):
    return struct.pack(f"<{len(values)}f", *values)


def pose_line(m):
    return " ".join(f"{v:.12e}" for v in m)


def c_api_open_input(choices=0, struct_size=0, threads=1, cuda_device=0, mask=0, strings=(), config=b""):
    out = struct.pack("<BBbbB", choices, struct_size, threads, cuda_device, mask)
    for s in strings:
        out += bytes([len(s)]) + s
    return out + config


def varint(n):
    out = b""
    while True:
        byte = n & 0x7F
        n >>= 7
        if n:
            out += bytes([byte | 0x80])
        else:
            return out + bytes([byte])


def tf_record(event):
    length = struct.pack("<Q", len(event))
    return length + struct.pack("<I", masked_crc32c(length)) + event + struct.pack("<I", masked_crc32c(event))


def tf_scalar_event(tag, step, value, wall_time=1.0e9):
    """A tf.Event (wall_time = 1, step = 2, summary = 5) holding one Summary.Value (tag 1, simple_value 2)."""
    tag = tag.encode()
    v = b"\x0a" + varint(len(tag)) + tag + b"\x15" + struct.pack("<f", value)
    summary = b"\x0a" + varint(len(v)) + v
    return b"\x09" + struct.pack("<d", wall_time) + b"\x10" + varint(step) + b"\x2a" + varint(len(summary)) + summary


def tf_version_event():
    text = b"brain.Event:2"
    return b"\x09" + struct.pack("<d", 1.0e9) + b"\x1a" + varint(len(text)) + text


def metrics_lines():
    iou = ", ".join(f'"c{c}": {0.05 * c:.6f}' for c in range(1, 12)) + ', "c12": null'
    confusion = "[" + ", ".join("[" + ", ".join(str(int(r == k) * 7) for k in range(12)) + "]" for r in range(12)) + "]"
    return [
        '{"type": "step", "epoch": 1, "step": 1, "loss": 2.5, "lr": 1.0e-3, "beta1": 0.95, "grad_norm": 3.2, "elapsed_s": 0.5}',
        '{"type": "step", "epoch": 1, "step": 2, "loss": 2.1, "lr": 1.0e-3, "beta1": 0.95, "grad_norm": 2.9, "elapsed_s": 1.0}',
        f'{{"type": "eval", "epoch": 1, "step": 2, "mode": "dense", "miou": 0.25, "labelled_cells": 100, "best_epoch": 1, "iou": {{{iou}}}, "confusion": {confusion}}}',
        '{"type": "epoch", "epoch": 1, "step": 2, "mean_loss": 2.3, "data_wait_s": 0.1, "checkpoint": "checkpoint.safetensors"}',
    ]


def npy_file(descr, shape, data, major=1, order="False"):
    """A NumPy .npy file: magic, version, header length, the dict padded to 64 bytes, the data."""
    text = f"{{'descr': '{descr}', 'fortran_order': {order}, 'shape': {shape}, }}"
    preamble = 10 if major == 1 else 12
    text = (text + " " * ((64 - (preamble + len(text) + 1) % 64) % 64) + "\n").encode()
    length = struct.pack("<H", len(text)) if major == 1 else struct.pack("<I", len(text))
    return b"\x93NUMPY" + bytes([major, 0]) + length + text + data


def pcd_header(fields, sizes, types, counts, points, data):
    return (f"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\n"
            f"TYPE {types}\nCOUNT {counts}\nWIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {points}\nDATA {data}\n").encode()


def lzf_literals(data):
    """A valid LZF stream of literal runs only (up to 32 bytes each)."""
    return b"".join(bytes([len(data[i:i + 32]) - 1]) + data[i:i + 32] for i in range(0, len(data), 32))


def point_format_seeds(points):
    """npy, nuscenes, pcd and ply files of the same points (x y z r), and near-valid variants."""
    n = len(points)
    xyzr = points_bytes(points)
    by_field = b"".join(struct.pack(f"<{n}f", *(p[k] for p in points)) for k in range(4))
    ply_head = ("ply\nformat {}\ncomment pillarseg fuzz seed\nelement vertex " + str(n) +
                "\nproperty float x\nproperty float y\nproperty float z\nproperty float intensity\n"
                "element face 1\nproperty list uchar int vertex_indices\nend_header\n")
    # The LZF stream of the binary_compressed seed: literals and both back-reference forms.
    xs, ys, zs, ints = [1.0, 1.0, 1.0, 2.0, 3.0], [4.0, 5.0, 6.0, 7.0, 8.0], [0.5] * 5, [10, 20, 30, 40, 50]
    expanded = struct.pack("<5f", *xs) + struct.pack("<5f", *ys) + struct.pack("<5f", *zs) + bytes(ints)
    lzf = (b"\x03" + expanded[0:4] + b"\xc0\x03" + bytes([27]) + expanded[12:40] + b"\x03" + expanded[40:44] +
           b"\xe0\x07\x03" + b"\x04" + expanded[60:65])
    padded = b"".join(struct.pack("<3f", 9, 9, 9) + struct.pack("<d", p[2]) + b"\xab\xcd\xef" +
                      struct.pack("<H", int(p[3] * 1000)) + struct.pack("<2f", p[0], p[1]) for p in points)
    return {
        "npy": {
            "f32_n4.npy": npy_file("<f4", f"({n}, 4)", xyzr),
            "f64_n3.npy": npy_file("<f8", f"({n}, 3)", b"".join(struct.pack("<3d", *p[:3]) for p in points), major=2),
            "be_f32_n5.npy": npy_file(">f4", f"({n}, 5)", b"".join(struct.pack(">5f", *p, 7.0) for p in points), major=3),
            "empty.npy": npy_file("<f4", "(0, 4)", b""),
            "fortran.npy": npy_file("<f4", f"({n}, 4)", xyzr, order="True"),
            "int32.npy": npy_file("<i4", f"({n}, 4)", xyzr),
            "truncated.npy": npy_file("<f4", f"({n}, 4)", xyzr)[:-5],
            "kitti_records.npy": xyzr,
        },
        "nuscenes": {
            "three_points.pcd.bin": b"".join(struct.pack("<5f", *p[:3], p[3] * 255, 31.0) for p in points),
            "empty.pcd.bin": b"",
            "bad_ring.pcd.bin": b"".join(struct.pack("<5f", *p, 0.5) for p in points),
            "kitti_records.pcd.bin": xyzr + xyzr[:4 * 4],
        },
        "pcd": {
            "binary.pcd": pcd_header("x y z intensity", "4 4 4 4", "F F F F", "1 1 1 1", n, "binary") + xyzr,
            "ascii_odd_order.pcd": pcd_header("y normal x reflectance z", "4 4 8 1 4", "F F F U F", "1 3 1 1 1", 3,
                                              "ascii") + b"-2.25 0 0 1 1.5 128 0.125\n12.5 0.5 0.5 0.5 -30 64 -1.75\r\n"
                                                         b"nan nan nan nan nan 0 nan\n",
            "binary_padding.pcd": pcd_header("normal z _ intensity x y", "4 8 1 2 4 4", "F F U U F F", "3 1 3 1 1 1",
                                             n, "binary") + padded,
            "compressed_backrefs.pcd": pcd_header("x y z intensity", "4 4 4 1", "F F F U", "1 1 1 1", 5,
                                                  "binary_compressed") + struct.pack("<II", len(lzf), 65) + lzf,
            "compressed_literals.pcd": pcd_header("x y z intensity", "4 4 4 4", "F F F F", "1 1 1 1", n,
                                                  "binary_compressed") +
                                       struct.pack("<II", len(lzf_literals(by_field)), len(by_field)) +
                                       lzf_literals(by_field),
            "no_z.pcd": pcd_header("x y w", "4 4 4", "F F F", "1 1 1", 0, "ascii"),
            "truncated.pcd": (pcd_header("x y z intensity", "4 4 4 4", "F F F F", "1 1 1 1", n, "binary") + xyzr)[:-3],
        },
        "ply": {
            "ascii.ply": (ply_head.format("ascii 1.0") + "".join(f"{p[0]!r} {p[1]!r} {p[2]!r} {p[3]!r}\n" for p in points) +
                          "3 0 1 2\n").encode(),
            "binary_le.ply": ply_head.format("binary_little_endian 1.0").encode() + xyzr + b"\x03" + struct.pack("<3i", 0, 1, 2),
            "binary_be.ply": ply_head.format("binary_big_endian 1.0").encode() +
                             b"".join(struct.pack(">4f", *p) for p in points) + b"\x03" + struct.pack(">3i", 0, 1, 2),
            "element_before_vertex.ply": b"ply\nformat ascii 1.0\nelement camera 1\nproperty float fov\n"
                                         b"property list uchar int ids\nelement vertex 2\nproperty double x\n"
                                         b"property double y\nproperty double z\nproperty list uchar float extra\n"
                                         b"property uchar i\nend_header\n60 2 7 8\n1 2 3 0 128\n-4 5 -6 2 0.5 0.5 64\n",
            "truncated.ply": (ply_head.format("binary_little_endian 1.0").encode() + xyzr)[:-7],
            "no_vertex.ply": b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int v\nend_header\n",
        },
    }


def converted_seeds(name, records):
    """A KITTI scan's records (16 bytes a point) as .npy, binary PCD, binary PLY and .pcd.bin seeds."""
    points = [struct.unpack_from("<4f", records, i) for i in range(0, len(records), 16)]
    n = len(points)
    return {
        "npy": {f"{name}.npy": npy_file("<f4", f"({n}, 4)", records)},
        "pcd": {f"{name}.pcd": pcd_header("x y z intensity", "4 4 4 4", "F F F F", "1 1 1 1", n, "binary") + records},
        "ply": {f"{name}.ply": (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\n"
                                "property float y\nproperty float z\nproperty float intensity\nend_header\n").encode() +
                               records},
        "nuscenes": {f"{name}.pcd.bin": b"".join(struct.pack("<5f", *p, 5.0) for p in points)},
    }


def hand_written_seeds():
    tiny = (FUZZ_DIR / "tiny_model.yaml").read_bytes()
    three = [(1.0, 2.0, -1.0, 0.5), (-3.0, 0.25, 0.0, 0.0), (10.0, -5.0, 0.5, 1.0)]
    strange = [(math.nan, 0, 0, 0), (math.inf, 1, 1, 0), (0, -math.inf, 0, 0), (0, 0, 0, math.nan),
               (3.0e38, -3.0e38, 1e30, 1e38), (1e-45, -0.0, 0.0, 0.0), (0.5, 0.5, 0.0, 0.3)]
    kitti_tr = [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02,
                -7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02,
                9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01]
    kitti_p0 = [7.188560e+02, 0, 6.071928e+02, 0, 0, 7.188560e+02, 1.852157e+02, 0, 0, 0, 1, 0]
    kitti_p1 = kitti_p0[:3] + [-3.861448e+02] + kitti_p0[4:]
    identity = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]
    moved = [9.999978e-01, 5.272628e-04, -2.066935e-03, -4.690294e-02, -5.296506e-04, 9.999992e-01,
             -1.154865e-03, -2.839928e-02, 2.066324e-03, 1.155958e-03, 9.999971e-01, 8.586941e-01]
    calib = "".join(f"P{i}: {pose_line(p)}\n" for i, p in enumerate([kitti_p0, kitti_p1, kitti_p0, kitti_p1]))
    calib += f"Tr: {pose_line(kitti_tr)}\n"

    all_dtypes = safetensors({
        "counter": ("I64", [], struct.pack("<q", 7)),
        "weight": ("F32", [2, 2], f32(1.0, -2.5, 0.0, math.inf)),
        "half": ("F16", [3], struct.pack("<3H", 0x3C00, 0x7C00, 0x0001)),
        "brain": ("BF16", [2], struct.pack("<2H", 0x3F80, 0xFFC1)),
        "empty": ("F32", [0, 4], b""),
    }, metadata={"format": "pillarseg-checkpoint-1", "note": "caf\u00e9 \ud83d\ude00"})
    checkpoint_metadata = {"format": "pillarseg-checkpoint-1", "config": tiny.decode(), "epoch": "1",
                           "step": "2", "best_miou": "0.25", "best_epoch": "1"}
    labelled = struct.pack("<Q", 2) + points_bytes(three[:2]) + bytes([1, 12])

    return {
        **point_format_seeds(three),
        "bin": {
            "three_points.bin": points_bytes(three),
            "empty.bin": b"",
            "non_finite.bin": points_bytes(strange),
            "truncated.bin": points_bytes(three) + b"\x01\x02\x03\x04\x05",
        },
        "label": {
            "four_labels.label": struct.pack("<4I", 10, 40, 0, (17 << 16) | 252),
            "three_labels.label": struct.pack("<3I", 10, 40, 9),
            "odd_size.label": b"\x0a\x00\x00\x00\x28\x00",
            "empty.label": b"",
        },
        "poses": {
            "kitti.txt": f"{pose_line(identity)}\n{pose_line(moved)}\n".encode(),
            "crlf_blank.txt": f"\r\n{pose_line(identity)}\r\n   \r\n{pose_line(moved)}".encode(),
            "eleven_numbers.txt": (pose_line(identity[:11]) + "\n").encode(),
            "not_finite.txt": ("1 0 0 nan 0 1 0 0 0 0 1 inf\n").encode(),
            "empty.txt": b"",
        },
        "calib": {
            "kitti.txt": calib.encode(),
            "tr_only.txt": f"Tr: {pose_line(identity)}".encode(),
            "no_tr.txt": f"P0: {pose_line(kitti_p0)}\n".encode(),
            "singular_tr.txt": f"Tr: {pose_line([0] * 12)}\n".encode(),
            "no_colon.txt": b"Tr 1 0 0 0 0 1 0 0 0 0 1 0\n",
        },
        "safetensors": {
            "one_tensor.safetensors": safetensors({"w": ("F32", [2], f32(0.5, -1.0))}),
            "all_dtypes.safetensors": all_dtypes,
            "no_tensors.safetensors": safetensors({}, metadata={"k": "v"}),
            "unpadded.safetensors": safetensors({"w": ("F32", [], f32(1.0))}, pad=False),
            "unsupported_dtype.safetensors": safetensors({"b": ("U8", [2], b"\x01\x02")}),
            "hole.safetensors": safetensors({"w": ("F32", [1], f32(1.0) + b"\x00" * 4)}),
        },
        "json": {
            "header.json": all_dtypes[8:8 + struct.unpack_from("<Q", all_dtypes)[0]].rstrip(b" "),
            "values.json": b' {"a": [1, -0, 9223372036854775807, -9223372036854775808, true, false, null],'
                           b' "s": "\\"\\\\\\/\\b\\f\\n\\r\\t\\u00e9\\ud83d\\ude00", "o": {"": {}}, "e": []} ',
            "utf8.json": '["caf\u00e9", "\u4e2d\u6587", "\U0001f600"]'.encode(),
            "nested.json": b"[" * 40 + b"]" * 40,
            "fraction.json": b"[1.5, 2e3]",
            "duplicate_key.json": b'{"a": 1, "a": 2}',
            "lone_surrogate.json": b'["\\ud800"]',
        },
        "run_config": {
            "small_cpu.yaml": (ROOT / "configs" / "small_cpu.yaml").read_bytes(),
            "pillar_3d_dense.yaml": (ROOT / "configs" / "pillar_3d_dense.yaml").read_bytes(),
            "gridmap_sparse.yaml": (ROOT / "configs" / "gridmap_sparse.yaml").read_bytes(),
            "tiny_model.yaml": tiny,
            "every_key.yaml": b"""grid: {x: [-12.8, 12.8], y: [-6.4, 6.4], z: [-2, 2], cell: 0.2, voxel_z: 0.5}
model: {max_points_per_pillar: 4, max_pillars: 100, pillars: true, pillar_channels: 8, occupancy: 3d,
        occupancy_channels: 4, grid_map: true, base_width: 8, depth: 3, upsampling: transposed,
        num_classes: 12}
train:
  ground_truth: dense
  loss: bce
  epochs: 2
  batch_size: 3
  seed: 18446744073709551615
  optimizer: {lr: 1e-4, weight_decay: 0, beta2: 0.999, eps: 1e-6, schedule: constant, div_factor: 25,
              pct_start: 0.3, moms: [0.9, 0.8], grad_clip: 0}
  augmentation: true
  coefficients: {vehicle: 3, person: 10, terrain: 0.5}
  sequences: [0, 2]
  max_scans_per_sequence: 10
  scan_stride: 2
  precise_bn_batches: 4
  workers: 2
eval: {sequences: [8, 9], scan_stride: 5, every_epochs: 1, mode: sparse}
input:
  reflectance: {scale: 0.00392157, offset: 0.1, clip: false}
  transform: {height: 0.11, roll: 1, pitch: -2, yaw: -90}
""",
            "input_matrix.yaml": b"input: {reflectance: none, transform: [[0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 1, 0.11], "
                                 b"[0, 0, 0, 1]]}\n",
            "input_singular.yaml": b"input: {transform: [1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}\n",
            "unknown_key.yaml": b"model: {base_widht: 8}\n",
            "empty.yaml": b"",
        },
        "class_table": {
            "override.yaml": b"classes:\n  - {id: 9, raw: [51, 80, 81, 52]}\n"
                             b"  - {id: 2, name: pedestrian, gt_weight: 7, color: [1, 2, 3]}\n"
                             b"moving: [252, 253, 254, 255, 256, 257, 258, 259]\n",
            "block_style.yaml": b"classes:\n  - id: 5\n    gt_weight: 10\n  - id: 0\n    raw: [0, 1]\n",
            "bad_id.yaml": b"classes:\n  - {id: 40}\n",
            "bad_color.yaml": b"classes:\n  - {id: 1, color: [256, 0]}\n",
            "raw_too_large.yaml": b"classes:\n  - {id: 1, raw: [65536]}\n",
            "empty.yaml": b"",
        },
        "cache_entry": {
            "gt_sparse_u8.psc": cache_entry("u8", [4, 8], bytes(range(12)) * 2 + bytes(8)),
            "observability_u32.psc": cache_entry("u32", [2, 3], struct.pack("<6I", 0, 1, 2, 3, 4, 70000)),
            "occupancy_f32.psc": cache_entry("f32", [2, 1, 2], f32(0.5, 0.0, 1.0, 0.25)),
            "neighbours_i64.psc": cache_entry("i64", [3], struct.pack("<3q", 0, 1, 2)),
            "dense_points_bytes.psc": cache_entry("bytes", [len(labelled)], labelled),
            "scalar_f32.psc": cache_entry("f32", [], f32(2.0)),
            "empty_u8.psc": cache_entry("u8", [0, 5], b""),
            "bad_checksum.psc": cache_entry("u8", [2], b"\x01\x02", checksum=0),
            "other_key.psc": cache_entry("u8", [1], b"\x01", key=CACHE_KEY.replace(b"frame=0", b"frame=1")),
        },
        "checkpoint": {
            "metadata_only.safetensors": safetensors({}, metadata=checkpoint_metadata),
            "bad_epoch.safetensors": safetensors({}, metadata={**checkpoint_metadata, "epoch": "1x"}),
        },
        "c_api_segment": {
            "three_points": b"\x00" + points_bytes(three),
            "probabilities": b"\x01" + points_bytes(three),
            "masked_probabilities": b"\x03" + points_bytes(three + [(0.1, 0.1, -1.0, 0.2)]),
            "non_finite": b"\x01" + points_bytes(strange),
            "no_points": b"\x00",
            "null_points_none": b"\x04" + struct.pack("<Q", 0),
            "null_points_some": b"\x04" + struct.pack("<Q", 5),
            "null_labels": b"\x08" + points_bytes(three),
        },
        "metrics_log": {
            "run.jsonl": "".join(line + "\n" for line in metrics_lines()).encode(),
            "cut_short.jsonl": ("\n".join(metrics_lines()[:3])[:-40]).encode(),
            "huge_numbers.jsonl": b'{"type": "step", "epoch": 99999999999999999999999, "step": -1}\n{"type": "other"}\n',
            "not_json.jsonl": b"{\"type\": \"step\", \"epoch\": 1,\n",
            "empty.jsonl": b"",
        },
        "tensorboard": {
            "run.tfevents": tf_record(tf_version_event()) + b"".join(
                tf_record(tf_scalar_event(tag, step, 1.0 / step)) for step in (1, 2, 3) for tag in ("train/loss", "train/lr")),
            "cut_short.tfevents": (tf_record(tf_version_event()) + tf_record(tf_scalar_event("train/loss", 1, 2.0)))[:-3],
            "bad_crc.tfevents": tf_record(tf_version_event())[:-1] + b"\x00",
            "empty.tfevents": b"",
        },
        "c_api_open": {
            "defaults": c_api_open_input(),
            "tiny_config": c_api_open_input(choices=0x80, config=tiny),
            "masked_emu": c_api_open_input(choices=0x01, mask=1),
            "bf16_cpu": c_api_open_input(choices=0x10),
            "cuda": c_api_open_input(choices=0x02),
            "strings": c_api_open_input(choices=0x3F, strings=(b"gpu", b"winograd", b"fp8")),
            "null_options": c_api_open_input(choices=0x40),
            "short_struct": c_api_open_input(struct_size=16, threads=-1),
            "negative_threads": c_api_open_input(threads=-3, cuda_device=-1),
            "other_model": c_api_open_input(choices=0x80, config=tiny.replace(b"base_width: 4", b"base_width: 8")),
            "other_grid": c_api_open_input(choices=0x80, config=tiny.replace(b"cell: 0.4", b"cell: 0.2")),
            # mask byte: bit 0 mask_unobserved, bits 1-2 flips 1, 2, 4 or the byte as a signed value.
            "flips_4": c_api_open_input(mask=0x04),
            "flips_2_masked_emu": c_api_open_input(choices=0x01, mask=0x03),
            "flips_bad": c_api_open_input(mask=0x86),
            "flips_asymmetric_grid": c_api_open_input(choices=0x80, mask=0x02,
                                                      config=tiny.replace(b"y: [-3.2, 3.2]", b"y: [-3.2, 4.8]")),
        },
    }


def run(cmd):
    subprocess.run([str(c) for c in cmd], check=True, stdout=subprocess.DEVNULL)


def engine_seeds(pillarseg):
    """Seeds from what `pillarseg simulate` and `pillarseg train` write (tiny_model.yaml)."""
    seeds = {k: {} for k in ("bin", "label", "poses", "calib", "cache_entry", "checkpoint", "c_api_segment",
                             "metrics_log", "tensorboard", "npy", "pcd", "ply", "nuscenes")}
    with tempfile.TemporaryDirectory(prefix="pillarseg-seeds-") as tmp:
        tmp = Path(tmp)
        data, cache, run_dir = tmp / "data", tmp / "cache", tmp / "run"
        run([pillarseg, "simulate", "--out", data, "--sequences", "1", "--scans", "2",
             "--points-per-scan", "30000", "--seed", "3"])
        run([pillarseg, "--threads", "1", "train", "--data", data, "--config", FUZZ_DIR / "tiny_model.yaml",
             "--out", run_dir, "--cache", cache])
        seq = data / "sequences" / "00"
        scan = (seq / "velodyne" / "000000.bin").read_bytes()
        labels = (seq / "labels" / "000000.label").read_bytes()
        # The 64 points nearest the sensor: they fall on the tiny grid.
        records = [scan[i:i + 16] for i in range(0, len(scan), 16)]
        order = sorted(range(len(records)), key=lambda i: sum(v * v for v in struct.unpack("<3f", records[i][:12])))
        near = sorted(order[:64])
        seeds["bin"]["simulated_64.bin"] = b"".join(records[i] for i in near)
        seeds["label"]["simulated_64.label"] = b"".join(labels[4 * i:4 * i + 4] for i in near)
        for reader, files in converted_seeds("simulated_64", seeds["bin"]["simulated_64.bin"]).items():
            seeds[reader].update(files)
        seeds["poses"]["simulated.txt"] = (seq / "poses.txt").read_bytes()
        seeds["calib"]["simulated.txt"] = (seq / "calib.txt").read_bytes()
        seeds["c_api_segment"]["simulated_64"] = b"\x01" + seeds["bin"]["simulated_64.bin"]
        for entry in sorted(cache.rglob("000000-*.psc")):
            _, rest = parse_cache_entry(entry.read_bytes())
            name = f"trained_{entry.parent.name}.psc"
            seeds["cache_entry"][name] = b"PSCACHE1" + struct.pack("<II", 1, len(CACHE_KEY)) + CACHE_KEY + rest
        trained = (run_dir / "checkpoint.safetensors").read_bytes()
        seeds["checkpoint"]["trained.safetensors"] = trained
        tensors, _ = read_safetensors(trained)
        weights_only = {k: v for k, v in tensors.items() if not k.startswith("optimizer.")}
        seeds["checkpoint"]["weights_only.safetensors"] = safetensors(weights_only)
        seeds["metrics_log"]["trained.jsonl"] = (run_dir / "metrics.jsonl").read_bytes()
        seeds["tensorboard"]["trained.tfevents"] = (run_dir / "events.out.tfevents.0.pillarseg").read_bytes()
    return seeds


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pillarseg", type=Path, help="a built pillarseg, for the simulated and trained seeds")
    parser.add_argument("--out", type=Path, default=FUZZ_DIR / "corpus")
    args = parser.parse_args()
    seeds = hand_written_seeds()
    if args.pillarseg:
        for reader, files in engine_seeds(args.pillarseg.resolve()).items():
            seeds[reader].update(files)
    for reader, files in seeds.items():
        directory = args.out / reader
        directory.mkdir(parents=True, exist_ok=True)
        for name, data in files.items():
            (directory / name).write_bytes(data)
        print(f"{reader}: {len(files)} seeds, {sum(map(len, files.values()))} bytes")


if __name__ == "__main__":
    main()
