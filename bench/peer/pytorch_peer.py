#!/usr/bin/python3
"""PyTorch peer of bench/bench_model.cpp: PillarSegNet (DESIGN.md section 2) in PyTorch, with the
module names of the authors' OpenPCDet model, timed on the CPU with the same input, size and
thread count as our engine.

  vfe.pfn_layers.0     OpenPCDet's PFNLayer: Linear(10 -> C, no bias) -> BatchNorm1d(eps 1e-3,
                       momentum 0.01) -> ReLU -> max over the N slots; points (P, N, 10) -> (P, C)
  scatter              OpenPCDet's PointPillarScatter: (P, C) + cells (P, 3: batch, iy, ix)
                       -> canvas (B, C, H, W), zeros where there is no pillar
  segmentation_head    milesial's U-Net without its input block `inc`: down1..down{depth},
                       up1..up{depth} (bilinear, or ConvTranspose 2x2/2), outc 1x1 -> 12 classes

Cases: `forward` (eval mode, under torch.no_grad()) and `train` (training-mode forward, the
loss over labelled cells, backward, gradient-norm clip 10, AdamW step) after one warm-up step;
`conv3x3`: single nn.Conv2d(I, O, 3, padding=1) layers, x (1, I, h, w), each warmed up once.
The timed steps: --reps of them (conv3x3: of each --shapes entry, one PEER_LAYER line each),
or with --serve one per command read from stdin until EOF, so that the caller can alternate
them with its own (bench_model does, so that a drifting machine load hits both sides alike):

  PEER_READY                           once the warm-up is done
  step              -> PEER_STEP wall_ms=... cpu_ms=...    (forward, train)
  conv3x3 I:O:h:w   -> PEER_STEP wall_ms=... cpu_ms=...    (conv3x3)

At the end one machine-readable line (then, with --profile, one more step under
torch.profiler, its ops by self CPU time as PEER_PROFILE lines):

  PEER key=value ...   (case, variant, threads, sizes, reps, median_ms, median_cpu_ms
                        (process CPU time, all threads), times_ms, gflop, gflops,
                        peak_rss_mb, params, torch)

gflop counts 2 x the multiply-adds of every Conv2d, ConvTranspose2d and Linear of one forward
(from their output shapes, recorded by forward hooks); a training step counts 3 x that (the
backward of each layer computes dx and dw, each as many multiply-adds as the forward).
peak_rss_mb is the peak resident memory of this process (VmHWM), which runs one case only.

Input: --inputs DIR with points.f32 (P, N, 10), cells.i32 (P, 3) and labels.u8 (B, H, W) as raw
little-endian arrays (bench_model writes them), or without --inputs a synthetic scan: --pillars
cells drawn with a density falling off with range from the sensor, like a LiDAR sweep.

Without torch (e.g. run by a python3 that lacks it) the script prints "skipped: ..." and exits 0.
"""

import argparse
import resource
import statistics
import sys
import time

try:
    import numpy as np
    import torch
    import torch.nn.functional as F
    from torch import nn
except ImportError as error:
    print(f"PEER skipped: python3-torch not installed ({error}); run with /usr/bin/python3")
    sys.exit(0)


class PFNLayer(nn.Module):
    """OpenPCDet's last PFNLayer (use_norm, last_layer): points (P, N, 10) -> (P, C)."""

    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.linear = nn.Linear(in_channels, out_channels, bias=False)
        self.norm = nn.BatchNorm1d(out_channels, eps=1e-3, momentum=0.01)

    def forward(self, inputs):
        x = self.linear(inputs)
        x = self.norm(x.permute(0, 2, 1)).permute(0, 2, 1)
        x = F.relu(x)
        return torch.max(x, dim=1)[0]


class PillarVFE(nn.Module):
    def __init__(self, channels):
        super().__init__()
        self.pfn_layers = nn.ModuleList([PFNLayer(10, channels)])

    def forward(self, points):
        return self.pfn_layers[0](points)


def scatter(features, cells, batch, height, width):
    """PointPillarScatter: features (P, C), cells (P, 3: batch, iy, ix) -> (B, C, H, W)."""
    channels = features.shape[1]
    canvas = features.new_zeros(channels, batch * height * width)
    index = (cells[:, 0] * height + cells[:, 1]) * width + cells[:, 2]
    canvas[:, index] = features.t()
    return canvas.view(channels, batch, height, width).permute(1, 0, 2, 3).contiguous()


class DoubleConv(nn.Module):
    """[Conv3x3 (bias) -> BatchNorm -> ReLU] x 2; (B, in, H, W) -> (B, out, H, W)."""

    def __init__(self, in_channels, out_channels, mid_channels=None):
        super().__init__()
        mid_channels = mid_channels or out_channels
        self.double_conv = nn.Sequential(
            nn.Conv2d(in_channels, mid_channels, kernel_size=3, padding=1),
            nn.BatchNorm2d(mid_channels),
            nn.ReLU(inplace=True),
            nn.Conv2d(mid_channels, out_channels, kernel_size=3, padding=1),
            nn.BatchNorm2d(out_channels),
            nn.ReLU(inplace=True),
        )

    def forward(self, x):
        return self.double_conv(x)


class Down(nn.Module):
    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.maxpool_conv = nn.Sequential(nn.MaxPool2d(2), DoubleConv(in_channels, out_channels))

    def forward(self, x):
        return self.maxpool_conv(x)


class Up(nn.Module):
    """Upsample x1, zero-pad it to the skip x2's size, cat [x2, x1], DoubleConv."""

    def __init__(self, in_channels, out_channels, bilinear):
        super().__init__()
        if bilinear:
            self.up = nn.Upsample(scale_factor=2, mode="bilinear", align_corners=True)
            self.conv = DoubleConv(in_channels, out_channels, in_channels // 2)
        else:
            self.up = nn.ConvTranspose2d(in_channels, in_channels // 2, kernel_size=2, stride=2)
            self.conv = DoubleConv(in_channels, out_channels)

    def forward(self, x1, x2):
        x1 = self.up(x1)
        diff_y = x2.size(2) - x1.size(2)
        diff_x = x2.size(3) - x1.size(3)
        x1 = F.pad(x1, [diff_x // 2, diff_x - diff_x // 2, diff_y // 2, diff_y - diff_y // 2])
        return self.conv(torch.cat([x2, x1], dim=1))


class OutConv(nn.Module):
    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size=1)

    def forward(self, x):
        return self.conv(x)


class UNet(nn.Module):
    """milesial's U-Net without `inc`, generalised to base width b and depth (b = 64, depth 4
    is UNet(64, 12) of the authors); (B, I, H, W) -> logits (B, classes, H, W)."""

    def __init__(self, in_channels, classes, base_width, depth, bilinear):
        super().__init__()
        factor = 2 if bilinear else 1
        widths = [in_channels] + [base_width << i for i in range(1, depth + 1)]
        widths[depth] //= factor
        self.depth = depth
        for i in range(1, depth + 1):
            setattr(self, f"down{i}", Down(widths[i - 1], widths[i]))
        for j in range(1, depth + 1):
            level = depth - j
            up_in = base_width << (level + 1)
            out = base_width if level == 0 else (base_width << level) // factor
            setattr(self, f"up{j}", Up(up_in, out, bilinear))
        self.outc = OutConv(base_width, classes)

    def forward(self, x):
        skips = [x]
        for i in range(1, self.depth + 1):
            skips.append(getattr(self, f"down{i}")(skips[-1]))
        x = skips[self.depth]
        for j in range(1, self.depth + 1):
            x = getattr(self, f"up{j}")(x, skips[self.depth - j])
        return self.outc(x)


class PillarSegNet(nn.Module):
    def __init__(self, args):
        super().__init__()
        self.batch, self.height, self.width = args.batch, args.height, args.width
        self.vfe = PillarVFE(args.pillar_channels)
        self.segmentation_head = UNet(args.pillar_channels, 12, args.base_width, args.depth,
                                      args.variant == "bilinear")

    def forward(self, points, cells):
        features = self.vfe(points)
        canvas = scatter(features, cells, self.batch, self.height, self.width)
        return self.segmentation_head(canvas)


def count_flops(model, flops):
    """Appends to `flops`, at each forward of a Conv2d, ConvTranspose2d or Linear of the model,
    2 x its multiply-adds; returns the hook handles."""

    def hook(module, inputs, output):
        if isinstance(module, nn.Conv2d):
            k = module.kernel_size[0] * module.kernel_size[1]
            flops.append(2 * output.numel() * module.in_channels * k)
        elif isinstance(module, nn.ConvTranspose2d):
            k = module.kernel_size[0] * module.kernel_size[1]
            flops.append(2 * inputs[0].numel() * module.out_channels * k)
        elif isinstance(module, nn.Linear):
            flops.append(2 * output.numel() * module.in_features)

    return [m.register_forward_hook(hook) for m in model.modules()
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d, nn.Linear))]


def synthetic_inputs(args, generator):
    """A LiDAR-like scan: up to --pillars distinct cells per sample, denser near the sensor (the
    grid centre), each with 1..N points, fewer far from the sensor."""
    rng = np.random.default_rng(args.seed)
    half_h, half_w = args.height / 2, args.width / 2
    cells = []
    for b in range(args.batch):
        radius = np.minimum(rng.exponential(0.25, 4 * args.pillars), 1.0)
        angle = rng.uniform(0, 2 * np.pi, 4 * args.pillars)
        iy = (half_h * (1 + radius * np.sin(angle))).astype(np.int64).clip(0, args.height - 1)
        ix = (half_w * (1 + radius * np.cos(angle))).astype(np.int64).clip(0, args.width - 1)
        flat = rng.permutation(np.unique(iy * args.width + ix))[:args.pillars]
        cells.append(np.stack([np.full_like(flat, b), flat // args.width, flat % args.width], 1))
    cells = np.concatenate(cells)
    distance = np.hypot((cells[:, 1] - half_h) / half_h, (cells[:, 2] - half_w) / half_w)
    most = np.maximum(1, np.round(args.points_per_pillar * (1 - np.minimum(distance, 1))))
    count = torch.from_numpy(1 + (rng.uniform(size=len(cells)) * most).astype(np.int64))
    points = torch.randn(len(cells), args.points_per_pillar, 10, generator=generator)
    points[torch.arange(args.points_per_pillar)[None, :] >= count[:, None]] = 0
    labels = torch.randint(0, 13, (args.batch, args.height, args.width), generator=generator)
    return points, torch.from_numpy(cells.astype(np.int64)), labels


def file_inputs(args):
    """Raw arrays written by bench_model: points.f32 (P, N, 10), cells.i32 (P, 3), labels.u8."""
    points = np.fromfile(f"{args.inputs}/points.f32", dtype="<f4")
    cells = np.fromfile(f"{args.inputs}/cells.i32", dtype="<i4")
    labels = np.fromfile(f"{args.inputs}/labels.u8", dtype=np.uint8)
    pillars = cells.size // 3
    expected = (pillars * args.points_per_pillar * 10, args.batch * args.height * args.width)
    if cells.size % 3 != 0 or (points.size, labels.size) != expected:
        sys.exit(f"pytorch_peer: {args.inputs} holds {points.size} point floats, {cells.size} cell"
                 f" ints and {labels.size} labels; expected {expected[0]}, 3 x P and {expected[1]}"
                 f" for P = {pillars}, N = {args.points_per_pillar}, B x H x W = {args.batch} x"
                 f" {args.height} x {args.width}")
    return (torch.from_numpy(points.reshape(pillars, args.points_per_pillar, 10)),
            torch.from_numpy(cells.reshape(pillars, 3).astype(np.int64)),
            torch.from_numpy(labels.reshape(args.batch, args.height, args.width).astype(np.int64)))


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", choices=["forward", "train", "conv3x3"], required=True)
    p.add_argument("--variant", choices=["bilinear", "transposed"], default="bilinear")
    p.add_argument("--threads", type=int, required=True, help="torch.set_num_threads")
    p.add_argument("--reps", type=int, default=3, help="timed steps after one warm-up")
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--height", type=int, default=500)
    p.add_argument("--width", type=int, default=1000)
    p.add_argument("--pillar-channels", type=int, default=64)
    p.add_argument("--base-width", type=int, default=64)
    p.add_argument("--depth", type=int, default=4)
    p.add_argument("--points-per-pillar", type=int, default=20)
    p.add_argument("--pillars", type=int, default=40000, help="synthetic input only, per sample")
    p.add_argument("--inputs", help="directory of points.f32, cells.i32, labels.u8")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--shapes", default="",
                   help="conv3x3 case: comma-separated I:O:h:w, x (1, I, h, w) -> (1, O, h, w)")
    p.add_argument("--serve", action="store_true",
                   help="after the warm-up, run a step per command on stdin (see the top)")
    p.add_argument("--profile", action="store_true",
                   help="after the timed steps, one more under torch.profiler: PEER_PROFILE lines")
    args = p.parse_args()
    if args.pillar_channels != args.base_width:
        # milesial's up{depth} takes 2b channels: b from below and the I = C input channels.
        p.error(f"the U-Net without `inc` needs --pillar-channels = --base-width, got"
                f" {args.pillar_channels} and {args.base_width}")
    if args.threads < 1 or args.reps < 1 or args.batch < 1:
        p.error(f"--threads, --reps and --batch must be >= 1, got {args.threads}, {args.reps},"
                f" {args.batch}")
    return args


def peak_rss_mb():
    """This process's peak resident memory: VmHWM in /proc/self/status. Not ru_maxrss: Linux
    carries the parent's peak into a child started by posix_spawn (through exec, which records
    the peak of the memory it replaces), so a peer of a large bench_model would report that."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def timed(step):
    """Wall and process CPU seconds (all threads) of one call of step()."""
    start, cpu_start = time.perf_counter(), time.process_time()
    step()
    return time.perf_counter() - start, time.process_time() - cpu_start


def serve(run_command):
    """--serve: prints PEER_READY, then for each line on stdin until EOF prints the PEER_STEP
    line of run_command(words of the line) -> (wall, cpu) seconds."""
    print("PEER_READY", flush=True)
    for line in sys.stdin:
        wall, cpu = run_command(line.split())
        print(f"PEER_STEP wall_ms={wall * 1e3:.1f} cpu_ms={cpu * 1e3:.1f}", flush=True)


def parse_shape(text):
    shape = tuple(int(v) for v in text.split(":"))
    if len(shape) != 4 or min(shape) < 1:
        sys.exit(f"pytorch_peer: a conv3x3 shape is I:O:h:w of positive sizes, got {text!r}")
    return shape


class Conv3x3Layer:
    """nn.Conv2d(I, O, 3, padding=1) in eval mode with a random input (1, I, h, w), run under
    no_grad; warmed up once when built."""

    def __init__(self, shape):
        in_channels, out_channels, height, width = shape
        self.x = torch.randn(1, in_channels, height, width)
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size=3, padding=1).eval()
        self()

    def __call__(self):
        with torch.no_grad():
            self.conv(self.x)


def conv3x3_case(args):
    """Single conv layers: with --serve, one timed run per "conv3x3 I:O:h:w" command (the layer
    is built and warmed up when its shape changes); otherwise --reps timed runs of each --shapes
    entry, one PEER_LAYER line each. Then a PEER line."""
    current = {}

    def run_command(words):
        if len(words) != 2 or words[0] != "conv3x3":
            sys.exit(f"pytorch_peer: expected the command 'conv3x3 I:O:h:w', got {words}")
        shape = parse_shape(words[1])
        if shape not in current:
            current.clear()
            current[shape] = Conv3x3Layer(shape)
        return timed(current[shape])

    if args.serve:
        serve(run_command)
    for shape in [parse_shape(entry) for entry in args.shapes.split(",") if entry]:
        layer = Conv3x3Layer(shape)
        times, cpu_times = zip(*[timed(layer) for _ in range(args.reps)])
        median, median_cpu = statistics.median(times), statistics.median(cpu_times)
        gflop = 2 * shape[0] * shape[1] * 9 * shape[2] * shape[3] * 1e-9
        print(f"PEER_LAYER in={shape[0]} out={shape[1]} height={shape[2]} width={shape[3]}"
              f" median_ms={median * 1e3:.1f} median_cpu_ms={median_cpu * 1e3:.1f}"
              f" gflops={gflop / median:.2f}", flush=True)
    print(f"PEER case=conv3x3 threads={args.threads} torch={torch.__version__}", flush=True)


def main():
    args = parse_args()
    torch.set_num_threads(args.threads)
    if args.case == "conv3x3":
        conv3x3_case(args)
        return
    generator = torch.Generator().manual_seed(args.seed)
    torch.manual_seed(args.seed)
    points, cells, labels = file_inputs(args) if args.inputs else synthetic_inputs(args, generator)
    model = PillarSegNet(args)
    params = sum(p.numel() for p in model.parameters())

    # Loss over labelled cells (label 0 is ignored): cross-entropy of class id - 1, each cell
    # weighted by its true class's coefficient, summed and divided by the labelled-cell count.
    coefficients = torch.tensor([2, 8, 8, 8, 1, 1, 1, 1, 1, 1, 1, 1], dtype=torch.float32)
    target = labels - 1
    labelled = max(int((labels > 0).sum()), 1)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, betas=(0.9, 0.99), eps=1e-8,
                                  weight_decay=0.01)

    def forward_eval():
        with torch.no_grad():
            model(points, cells)

    def train_step():
        logits = model(points, cells)
        loss = F.cross_entropy(logits, target, weight=coefficients, ignore_index=-1,
                               reduction="sum") / labelled
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
        optimizer.step()

    step = forward_eval if args.case == "forward" else train_step
    model.train(args.case == "train")
    # Warm-up (first touch of the activation memory, oneDNN's kernel generation), counting the
    # forward's FLOPs on the way.
    flops = []
    handles = count_flops(model, flops)
    step()
    for handle in handles:
        handle.remove()
    gflop = sum(flops) * 1e-9
    step_gflop = gflop if args.case == "forward" else 3 * gflop

    times, cpu_times = [], []

    def run_command(words):
        if words != ["step"]:
            sys.exit(f"pytorch_peer: expected the command 'step', got {words}")
        wall, cpu = timed(step)
        times.append(wall)
        cpu_times.append(cpu)
        return wall, cpu

    if args.serve:
        serve(run_command)
    else:
        for _ in range(args.reps):
            run_command(["step"])
    median = statistics.median(times) if times else float("nan")
    fields = {
        "case": args.case, "variant": args.variant, "threads": args.threads,
        "batch": args.batch, "height": args.height, "width": args.width,
        "pillars": points.shape[0], "points_per_pillar": args.points_per_pillar,
        "pillar_channels": args.pillar_channels, "base_width": args.base_width,
        "reps": len(times), "median_ms": f"{median * 1e3:.1f}",
        "median_cpu_ms": f"{statistics.median(cpu_times) * 1e3 if times else median:.1f}",
        "times_ms": ",".join(f"{t * 1e3:.1f}" for t in times) or "-",
        "gflop": f"{step_gflop:.2f}", "gflops": f"{step_gflop / median:.2f}",
        "peak_rss_mb": f"{peak_rss_mb():.0f}", "params": params, "torch": torch.__version__,
    }
    print("PEER " + " ".join(f"{k}={v}" for k, v in fields.items()), flush=True)
    if args.profile:
        with torch.profiler.profile() as profile:
            step()
        table = profile.key_averages().table(sort_by="self_cpu_time_total", row_limit=15)
        for line in table.splitlines():
            print("PEER_PROFILE " + line, flush=True)


if __name__ == "__main__":
    main()
