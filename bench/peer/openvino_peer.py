#!/usr/bin/env python3
"""The segmentation U-Net of PillarSegNet in OpenVINO against ours, on the CPU, in one run.

The network (the authors' UNet: DoubleConv 3x3 + BatchNorm + ReLU blocks, 2x2 max-pool, bilinear
x2 upsampling with align_corners, zero padding to the skip's size, concatenation, a 1x1 head) is
written as ONNX with the `onnx` helper API (PyTorch is not needed; the graph is the one
pytorch_peer.py's UNet exports: the same ops, shapes and layouts) and compiled by OpenVINO for
the CPU twice: INFERENCE_PRECISION_HINT f32, and bf16 (which OpenVINO keeps only on CPUs with
AVX512_BF16 or AMX; elsewhere it runs f32, and the report says which it ran). Ours is `pillarseg
bench --device cpu` on the same input size and thread count: its "U-Net" and "head" stages, in
FP32 and with `--precision bf16` (our AVX512_BF16 micro-kernel; on CPUs without it ours falls
back to FP32 with a warning, and the report says which ours ran). The sides alternate round by
round and the medians are reported, with the ratios.

    python3 bench/peer/openvino_peer.py --pillarseg build/pillarseg --threads 2 --rounds 5

Prints "skipped: ..." and exits 0 where openvino or onnx is missing.
"""
import argparse
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time

try:
    import numpy as np
    import onnx
    from onnx import TensorProto, helper, numpy_helper
    import openvino as ov
except ImportError as e:  # pragma: no cover - depends on the machine
    print(f"skipped: {e} (pip install openvino onnx)")
    sys.exit(0)


class Builder:
    """ONNX nodes and initializers of the U-Net, named like the authors' module."""

    def __init__(self, seed):
        self.nodes, self.inits = [], []
        self.rng = np.random.default_rng(seed)
        self.count = 0

    def name(self, prefix):
        self.count += 1
        return f"{prefix}_{self.count}"

    def init(self, name, array):
        self.inits.append(numpy_helper.from_array(array.astype(np.float32), name))
        return name

    def conv(self, x, cin, cout, k, pad, bias=True):
        w = self.init(self.name("w"), self.rng.normal(0, (2.0 / (cin * k * k)) ** 0.5, (cout, cin, k, k)))
        inputs = [x, w]
        if bias:
            inputs.append(self.init(self.name("b"), np.zeros(cout)))
        y = self.name("conv")
        self.nodes.append(helper.make_node("Conv", inputs, [y], kernel_shape=[k, k], pads=[pad] * 4))
        return y

    def bn_relu(self, x, c):
        scale = self.init(self.name("g"), np.ones(c))
        bias = self.init(self.name("beta"), np.zeros(c))
        mean = self.init(self.name("mean"), self.rng.normal(0, 0.1, c))
        var = self.init(self.name("var"), np.ones(c))
        y, z = self.name("bn"), self.name("relu")
        self.nodes.append(helper.make_node("BatchNormalization", [x, scale, bias, mean, var], [y], epsilon=1e-5))
        self.nodes.append(helper.make_node("Relu", [y], [z]))
        return z

    def double_conv(self, x, cin, cout, mid=None):
        mid = mid or cout
        return self.bn_relu(self.conv(self.bn_relu(self.conv(x, cin, mid, 3, 1, False), mid), mid, cout, 3, 1, False),
                            cout)

    def maxpool(self, x):
        y = self.name("pool")
        self.nodes.append(helper.make_node("MaxPool", [x], [y], kernel_shape=[2, 2], strides=[2, 2]))
        return y

    def upsample(self, x):
        scales = self.init(self.name("scales"), np.array([1, 1, 2, 2]))
        y = self.name("up")
        self.nodes.append(helper.make_node("Resize", [x, "", scales], [y], mode="linear",
                                           coordinate_transformation_mode="align_corners"))
        return y

    def pad_to(self, x, dh, dw):
        if dh == 0 and dw == 0:
            return x
        pads = self.name("pads")
        self.inits.append(numpy_helper.from_array(
            np.array([0, 0, dh // 2, dw // 2, 0, 0, dh - dh // 2, dw - dw // 2], dtype=np.int64), pads))
        y = self.name("pad")
        self.nodes.append(helper.make_node("Pad", [x, pads], [y], mode="constant"))
        return y

    def concat(self, a, b):
        y = self.name("cat")
        self.nodes.append(helper.make_node("Concat", [a, b], [y], axis=1))
        return y


def unet_onnx(channels, classes, base, depth, height, width, seed):
    """The bilinear UNet(channels, classes) of milesial's Pytorch-UNet without its input block,
    as PillarSegNet uses it: levels base * 2^i, the deepest halved for bilinear upsampling."""
    b = Builder(seed)
    x = "canvas"
    widths = [channels] + [base * 2 ** i for i in range(1, depth + 1)]
    widths[depth] //= 2  # bilinear: the bottom level has half the channels
    skips, sizes = [x], [(height, width)]
    h, w = height, width
    for i in range(1, depth + 1):
        h, w = h // 2, w // 2
        x = b.double_conv(b.maxpool(x), widths[i - 1], widths[i])
        skips.append(x)
        sizes.append((h, w))
    current, current_c = x, widths[depth]
    for j in range(1, depth + 1):
        level = depth - j
        skip, skip_c = skips[level], widths[level]
        out_c = widths[level] // 2 if j < depth else widths[level]
        up = b.upsample(current)
        uh, uw = 2 * sizes[level + 1][0], 2 * sizes[level + 1][1]
        up = b.pad_to(up, sizes[level][0] - uh, sizes[level][1] - uw)
        current = b.double_conv(b.concat(skip, up), skip_c + current_c, out_c, (skip_c + current_c) // 2)
        current_c = out_c
    logits = b.conv(current, current_c, classes, 1, 0)
    graph = helper.make_graph(
        b.nodes, "pillarsegnet_unet",
        [helper.make_tensor_value_info("canvas", TensorProto.FLOAT, [1, channels, height, width])],
        [helper.make_tensor_value_info(logits, TensorProto.FLOAT, [1, classes, height, width])], b.inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    onnx.checker.check_model(model)
    return model


def ours_ms(args, precision):
    """Our U-Net + head stage times (ms) of one `pillarseg bench` run (after its warm-up), and the
    precision it ran."""
    out = subprocess.run([args.pillarseg, "--threads", str(args.threads), "bench", "--device", "cpu",
                          "--precision", precision, "--repeat", "1"] +
                         (["--config", args.config] if args.config else []),
                         capture_output=True, text=True, check=True).stdout
    stages = dict(re.findall(r"^(U-Net|head)\s+([0-9.]+)$", out, re.M))
    ran = re.search(r"precision (fp32|bf16|fp16)", out)
    return float(stages["U-Net"]) + float(stages["head"]), ran.group(1) if ran else "?"


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pillarseg", required=True, help="our pillarseg binary")
    p.add_argument("--config", default="", help="a run config for both (default: the paper's full size)")
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--height", type=int, default=500)
    p.add_argument("--width", type=int, default=1000)
    p.add_argument("--channels", type=int, default=64, help="the canvas's channels (C)")
    p.add_argument("--base-width", type=int, default=64)
    p.add_argument("--depth", type=int, default=4)
    args = p.parse_args()

    core = ov.Core()
    cpu = core.get_property("CPU", "FULL_DEVICE_NAME")
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "unet.onnx")
        onnx.save(unet_onnx(args.channels, 12, args.base_width, args.depth, args.height, args.width, 0), path)
        model = core.read_model(path)
        compiled = {}
        for hint in ("f32", "bf16"):
            compiled[hint] = core.compile_model(model, "CPU", {"INFERENCE_PRECISION_HINT": hint,
                                                               "INFERENCE_NUM_THREADS": args.threads,
                                                               "PERFORMANCE_HINT": "LATENCY"})
    canvas = np.random.default_rng(1).standard_normal((1, args.channels, args.height, args.width)).astype(np.float32)
    requests = {hint: c.create_infer_request() for hint, c in compiled.items()}
    for r in requests.values():
        r.infer({"canvas": canvas})  # warm-up
    ours_ms(args, "fp32")  # warm-up
    times = {"ours": [], "ours_bf16": [], "f32": [], "bf16": []}
    ours_ran = "?"
    for _ in range(args.rounds):
        times["ours"].append(ours_ms(args, "fp32")[0])
        ms, ours_ran = ours_ms(args, "bf16")
        times["ours_bf16"].append(ms)
        for hint, r in requests.items():
            start = time.perf_counter()
            r.infer({"canvas": canvas})
            times[hint].append((time.perf_counter() - start) * 1e3)
    def type_name(t):
        return t.get_type_name() if hasattr(t, "get_type_name") else str(t)

    ran = {hint: type_name(c.get_property("INFERENCE_PRECISION_HINT")) for hint, c in compiled.items()}
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"U-Net {args.channels} -> 12 classes, b {args.base_width}, depth {args.depth}, "
          f"{args.height} x {args.width}, {args.threads} threads, CPU: {cpu} ({platform.machine()}); "
          f"OpenVINO {ov.__version__}; median of {args.rounds} alternating rounds")
    print(f"ours fp32 (U-Net + head stages): {med['ours']:.1f} ms")
    print(f"ours --precision bf16 (ran {ours_ran}): {med['ours_bf16']:.1f} ms")
    print(f"OpenVINO, hint f32 (ran {ran['f32']}): {med['f32']:.1f} ms; ours fp32 / OpenVINO = "
          f"{med['ours'] / med['f32']:.2f}")
    print(f"OpenVINO, hint bf16 (ran {ran['bf16']}): {med['bf16']:.1f} ms; ours bf16 / OpenVINO = "
          f"{med['ours_bf16'] / med['bf16']:.2f}")
    print(f"PEER case=unet threads={args.threads} ours_ms={med['ours']:.1f} ours_bf16_ms={med['ours_bf16']:.1f} "
          f"ours_bf16_ran={ours_ran} openvino_f32_ms={med['f32']:.1f} "
          f"openvino_bf16_ms={med['bf16']:.1f} openvino_bf16_ran={ran['bf16']}")


if __name__ == "__main__":
    main()
