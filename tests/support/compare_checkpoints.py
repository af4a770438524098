#!/usr/bin/env python3
"""Compares two pillarseg checkpoints (safetensors) tensor by tensor, with the standard library
only: prints the largest absolute difference of the F32 tensors, the difference of the whole
parameter vector relative to its norm, and exits 1 if either exceeds the given limits.
Usage: compare_checkpoints.py A B [--max-abs X] [--max-rel Y] [--only PREFIX] [--exclude REGEX]
The relative difference is per tensor (|a - b| / |a| in the 2-norm); the worst tensor's counts."""
import argparse
import array
import json
import math
import re
import struct
import sys


def read_safetensors(path):
    with open(path, "rb") as f:
        data = f.read()
    (header_len,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8:8 + header_len])
    body = data[8 + header_len:]
    tensors = {}
    for name, info in header.items():
        if name == "__metadata__" or info["dtype"] != "F32":
            continue
        begin, end = info["data_offsets"]
        values = array.array("f")
        values.frombytes(body[begin:end])
        if sys.byteorder != "little":
            values.byteswap()
        tensors[name] = values
    return tensors


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("a")
    parser.add_argument("b")
    parser.add_argument("--max-abs", type=float, default=math.inf)
    parser.add_argument("--max-rel", type=float, default=math.inf)
    parser.add_argument("--only", default="", help="compare the tensors whose names start with this")
    parser.add_argument("--exclude", default=None, help="leave out the tensors whose names match this regex")
    args = parser.parse_args()
    a, b = read_safetensors(args.a), read_safetensors(args.b)

    def chosen(name):
        return name.startswith(args.only) and not (args.exclude and re.search(args.exclude, name))

    names = sorted(n for n in a if chosen(n))
    if sorted(n for n in b if chosen(n)) != names:
        print(f"{args.a} and {args.b} hold different tensors")
        return 1
    worst, worst_name, rel, rel_name = 0.0, "", 0.0, ""
    for name in names:
        if len(a[name]) != len(b[name]):
            print(f"{name}: {len(a[name])} against {len(b[name])} values")
            return 1
        diff_sq, norm_sq = 0.0, 0.0
        for x, y in zip(a[name], b[name]):
            d = abs(x - y)
            if not d <= worst:  # NaN counts as the worst
                worst, worst_name = d, name
            diff_sq += (x - y) ** 2
            norm_sq += x * x
        r = math.sqrt(diff_sq / norm_sq) if norm_sq > 0 else math.sqrt(diff_sq)
        if not r <= rel:
            rel, rel_name = r, name
    print(f"{len(names)} tensors: largest |difference| {worst:.3e} ({worst_name}), largest relative difference "
          f"{rel:.3e} ({rel_name})")
    if not (worst <= args.max_abs and rel <= args.max_rel):
        print(f"beyond the limits (|difference| <= {args.max_abs:g}, relative <= {args.max_rel:g})")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
