#!/usr/bin/env python3
"""The segmentation U-Net of PillarSegNet in OpenVINO against ours, on the CPU, in one run.

The network (the authors' UNet: DoubleConv 3x3 + BatchNorm + ReLU blocks, 2x2 max-pool, bilinear
x2 upsampling with align_corners, zero padding to the skip's size, concatenation, a 1x1 head) is
written as ONNX with the `onnx` helper API (PyTorch is not needed; the graph is the one
pytorch_peer.py's UNet exports: the same ops, shapes and layouts, random weights) and compiled by
OpenVINO for the CPU three times: INFERENCE_PRECISION_HINT f32; bf16 (which OpenVINO keeps only on
CPUs with AVX512_BF16 or AMX; elsewhere it runs f32); and INT8, NNCF's post-training quantization
(nncf.quantize, default preset) of the same model, calibrated on the U-Net's real input: the
canvases of `--calibration-scans` simulated scans (`pillarseg simulate`, then `pillarseg bench
--scan S --save-canvas S.npy` for each), compiled with OpenVINO's default precision hint. What each
compiled model really runs is read from its execution graph: the runtime precision of every
convolution.

Ours is `pillarseg bench --device cpu` on its default scan (a simulated full-size scan), whose
canvas is also OpenVINO's input: its "U-Net" and "head" stages, in FP32, `--precision bf16` and
`--precision int8`, each reported with the precision and kernels it said it ran. Where ours
refuses a precision, its row says "not available" with our error line, and the others still run.
The sides alternate round by round; the medians are reported, with the ratios ours / OpenVINO.

    python3 -m venv bench/peer/.venv && bench/peer/.venv/bin/pip install openvino nncf onnx numpy
    bench/peer/.venv/bin/python bench/peer/openvino_peer.py --pillarseg build/pillarseg --threads 2 --rounds 5

Prints "skipped: ..." and exits 0 where numpy, onnx or openvino is missing; without nncf it
prints OpenVINO's INT8 row as skipped and runs the rest.
"""
import argparse
import collections
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
    print(f"skipped: {e} (pip install openvino nncf onnx numpy: bench/peer/README.md)")
    sys.exit(0)
NNCF_MISSING = None
try:
    import nncf
except ImportError as e:  # pragma: no cover - depends on the machine
    nncf = None
    NNCF_MISSING = f"{e} (pip install nncf)"


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


class OursFailed(Exception):
    """`pillarseg bench` exited with an error; the message is its first line of output."""


def pillarseg(args, *command):
    """Runs our binary with the bench's threads; its standard output, or OursFailed."""
    run = subprocess.run([args.pillarseg, "--threads", str(args.threads), *command], capture_output=True, text=True)
    if run.returncode != 0:
        lines = [line.strip() for line in (run.stderr + run.stdout).splitlines() if line.strip()]
        raise OursFailed(lines[0] if lines else f"exit status {run.returncode}")
    return run.stdout


def bench(args, precision, *extra):
    """One `pillarseg bench --device cpu` run (one warm-up, then --repeat timed repetitions, their
    median): U-Net + head stage time (ms), and the precision its header line says it ran (with its
    kernels, e.g. "bf16 (amx_bf16: 17 convolutions BF16)")."""
    out = pillarseg(args, "bench", "--device", "cpu", "--precision", precision, "--repeat", str(args.repeat),
                    *(["--config", args.config] if args.config else []), *extra)
    stages = dict(re.findall(r"^(U-Net|head)\s+([0-9.]+)$", out, re.M))
    ran = re.search(r"^pillarseg bench: device \S+, precision ([a-z0-9]+(?: \((?:[^()]|\([^()]*\))*\))?)", out, re.M)
    return float(stages["U-Net"]) + float(stages["head"]), ran.group(1) if ran else "?"


def calibration_canvases(args, tmp):
    """The U-Net's FP32 input canvases of `--calibration-scans` simulated scans, as NNCF's data set."""
    root = os.path.join(tmp, "calibration")
    pillarseg(args, "simulate", "--out", root, "--sequences", "1", "--scans", str(args.calibration_scans),
              "--seed", str(args.calibration_seed))
    velodyne = os.path.join(root, "sequences", "00", "velodyne")
    canvases = []
    for name in sorted(os.listdir(velodyne)):
        path = os.path.join(tmp, name + ".npy")
        bench(args, "fp32", "--scan", os.path.join(velodyne, name), "--save-canvas", path)
        canvases.append(np.load(path))
        os.remove(path)
    return canvases


def convolutions_by_precision(compiled):
    """How many convolutions of a compiled model's execution graph run in each precision."""
    counts = collections.Counter()
    for op in compiled.get_runtime_model().get_ordered_ops():
        info = op.get_rt_info()
        if info["layerType"].astype(str) == "Convolution":
            counts[info["runtimePrecision"].astype(str)] += 1
    return ", ".join(f"{n} {precision}" for precision, n in counts.most_common())


def agreement(logits, reference, occupied):
    """Percentage of the cells with points where two (1, classes, H, W) logits have the same arg-max."""
    return 100.0 * np.mean(logits[0].argmax(0)[occupied] == reference[0].argmax(0)[occupied])


def cpu_line():
    """The CPU's model name and the flags these figures depend on, as lscpu shows them."""
    name, flags = platform.processor() or "unknown", set()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name":
                    name = value.strip()
                elif key.strip() == "flags":
                    flags = set(value.split())
    except OSError:
        pass
    wanted = ["avx512f", "avx512_vnni", "avx512_bf16", "avx_vnni", "amx_tile", "amx_bf16", "amx_int8"]
    present = " ".join(f for f in wanted if f in flags) or "none of " + " ".join(wanted)
    return f"{name} ({platform.machine()}; flags: {present})"


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pillarseg", required=True, help="our pillarseg binary")
    p.add_argument("--config", default="", help="a run config for ours (default: the paper's full size); the ONNX "
                   "U-Net takes the shape of its canvas")
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--repeat", type=int, default=3,
                   help="timed runs a round on each side (ours: pillarseg bench --repeat, after its warm-up), "
                        "their median; the rounds' medians are reported")
    p.add_argument("--base-width", type=int, default=64)
    p.add_argument("--depth", type=int, default=4)
    p.add_argument("--calibration-scans", type=int, default=4,
                   help="simulated scans whose canvases calibrate OpenVINO's INT8 (NNCF's subset size)")
    p.add_argument("--calibration-seed", type=int, default=7,
                   help="`pillarseg simulate --seed` of the calibration scans (ours times the scan of seed 1)")
    args = p.parse_args()

    load_before = os.getloadavg()[0]  # the machine is shared: how busy it was around the figures
    core = ov.Core()
    compile_options = {"INFERENCE_NUM_THREADS": args.threads, "PERFORMANCE_HINT": "LATENCY"}
    with tempfile.TemporaryDirectory() as tmp:
        # Our warm-up, which also writes the canvas of the scan ours is timed on: OpenVINO's input.
        path = os.path.join(tmp, "canvas.npy")
        bench(args, "fp32", "--save-canvas", path)
        canvas = np.load(path)
        _, channels, height, width = canvas.shape
        onnx_path = os.path.join(tmp, "unet.onnx")
        onnx.save(unet_onnx(channels, 12, args.base_width, args.depth, height, width, 0), onnx_path)
        model = core.read_model(onnx_path)
        compiled = {hint: core.compile_model(model, "CPU", {**compile_options, "INFERENCE_PRECISION_HINT": hint})
                    for hint in ("f32", "bf16")}
        int8_missing = NNCF_MISSING if nncf is None else None
        if nncf is not None:
            canvases = calibration_canvases(args, tmp)
            start = time.perf_counter()
            quantized = nncf.quantize(model, nncf.Dataset(canvases), subset_size=len(canvases))
            quantize_s = time.perf_counter() - start
            del canvases
            compiled["int8"] = core.compile_model(quantized, "CPU", compile_options)
    requests = {hint: c.create_infer_request() for hint, c in compiled.items()}
    logits = {hint: next(iter(r.infer({"canvas": canvas}).values())).copy() for hint, r in requests.items()}  # warm-up
    occupied = (canvas[0] != 0).any(axis=0)

    ours = {"fp32": None, "bf16": None, "int8": None}  # what each ran, or why it did not
    ours_error = {}
    for precision in ours:
        try:
            ours[precision] = bench(args, precision)[1]
        except OursFailed as e:
            ours_error[precision] = str(e)
    times = collections.defaultdict(list)
    for _ in range(args.rounds):
        for precision in ours:
            if precision not in ours_error:
                times["ours " + precision].append(bench(args, precision)[0])
        for hint, r in requests.items():
            runs = []
            for _ in range(args.repeat):  # as ours: the median of --repeat runs a round
                start = time.perf_counter()
                r.infer({"canvas": canvas})
                runs.append((time.perf_counter() - start) * 1e3)
            times["openvino " + hint].append(statistics.median(runs))
    med = {k: statistics.median(v) for k, v in times.items()}

    print(f"U-Net {channels} -> 12 classes, b {args.base_width}, depth {args.depth}, {height} x {width}, "
          f"{args.threads} threads; CPU: {cpu_line()}; OpenVINO {ov.__version__}"
          f"{'' if nncf is None else ', NNCF ' + nncf.__version__}; median of {args.rounds} alternating rounds "
          f"(each the median of {args.repeat} runs); "
          f"input: the canvas of ours' benched scan ({occupied.sum()} cells with points); load average "
          f"{load_before:.1f} before, {os.getloadavg()[0]:.1f} after; random weights on both sides")
    if nncf is not None:
        print(f"OpenVINO INT8: nncf.quantize (default preset) calibrated on the canvases of {args.calibration_scans} "
              f"simulated scans (pillarseg simulate --seed {args.calibration_seed}), {quantize_s:.0f} s")
    for hint in ("f32", "bf16", "int8"):
        ours_precision = "fp32" if hint == "f32" else hint
        ours_key = "ours " + ours_precision
        if ours_precision in ours_error:
            ours_text = f"ours --precision {ours_precision}: not available: {ours_error[ours_precision]}"
        else:
            ours_text = f"ours --precision {ours_precision} (ran {ours[ours_precision]}): {med[ours_key]:.1f} ms"
        if hint not in compiled:
            print(f"{ours_text}; OpenVINO {hint}: skipped: {int8_missing}")
            continue
        c = compiled[hint]
        ran = c.get_property("INFERENCE_PRECISION_HINT")
        ran = ran.get_type_name() if hasattr(ran, "get_type_name") else str(ran)
        ov_text = (f"OpenVINO {hint} (precision hint {ran}; convolutions: {convolutions_by_precision(c)}): "
                   f"{med['openvino ' + hint]:.1f} ms")
        if hint != "f32":
            ov_text += f", arg-max equal to OpenVINO f32's on {agreement(logits[hint], logits['f32'], occupied):.2f}%"
        ratio = ("" if ours_precision in ours_error
                 else f"; ours / OpenVINO = {med[ours_key] / med['openvino ' + hint]:.2f}")
        print(f"{ours_text}; {ov_text}{ratio}")
    fields = [f"case=unet threads={args.threads}"]
    for key in ("ours fp32", "ours bf16", "ours int8", "openvino f32", "openvino bf16", "openvino int8"):
        fields.append(f"{key.replace(' ', '_')}_ms={med[key]:.1f}" if key in med else f"{key.replace(' ', '_')}_ms=na")
    print("PEER " + " ".join(fields))


if __name__ == "__main__":
    main()
