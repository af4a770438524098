#!/usr/bin/python3
"""Golden files for tests/test_golden.cpp: PillarSegNet built in PyTorch, run once, saved.

Each variant is a tiny PillarSegNet (DESIGN.md section 2) with random weights and inputs.
The network is written here with the module names of the authors' code (OpenPCDet's
PillarVFE/PFNLayer and PointPillarScatter, milesial's U-Net without its input block), so its
state_dict keys are the engine's parameter names. The script computes, in float64 from the
float32 values it saves, so that the references carry no float32 rounding of their own:

  training-mode forward -> logits, loss, every parameter gradient, running statistics;
  eval-mode forward (with the updated running statistics) -> logits;
  two AdamW steps (the gradient recomputed by a second training forward before step 2)
  -> parameters, Adam moments, running statistics and counters.

It writes two safetensors files per variant beside itself, by hand (8-byte little-endian
header length, JSON header, raw little-endian data; no extra packages): the golden file, and
weights_only_<variant>.safetensors, the initial state_dict alone with no metadata, as a PyTorch
user exports a model. The golden file's keys:

  param.<name>        the initial state_dict (F32; num_batches_tracked I64, shape ())
  input.pillar_points (P, N, 10) F32, padding slots zero
  input.pillar_cells  (P, 3) I64: sample, iy, ix (distinct cells within a sample)
  input.occupancy     (B, 1 or Z, H, W) F32, when the variant has the occupancy stream
  input.grid_map      (B, 6, H, W) F32, when the variant has the grid-map input
  input.labels        (B, H, W) I64, class ids 0..12 (0 = unlabelled)
  input.coefficients  (13) F32, loss coefficient per class id
  out.logits_train    (B, 12, H, W) training-mode logits
  out.loss            () loss of that forward
  grad.<param>        gradient of every trainable parameter
  out.buffer.<name>   running statistics and counters after the training forward
  out.logits_eval     (B, 12, H, W) eval-mode logits after that forward
  out.loss_step2      () loss of the second training forward (after one Adam step)
  after_adam.<name>   the whole state_dict after the two steps
  adam_m.<param>, adam_v.<param>  AdamW's exp_avg and exp_avg_sq after the two steps

The file's __metadata__ holds the model as a YAML config ("config", the engine's `grid:` and
`model:` keys), the loss ("ce" or "bce") and the AdamW hyper-parameters.

Run with Debian's python3 (it has torch and numpy): /usr/bin/python3 tests/golden/make_golden.py
"""

import json
import pathlib
import struct

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

NUM_CLASSES = 12
POINT_FEATURES = 10
ADAM = {"lr": 1e-2, "beta1": 0.9, "beta2": 0.99, "eps": 1e-8, "weight_decay": 0.01}
ADAM_STEPS = 2


# ---- OpenPCDet: PillarVFE with one PFNLayer (use_norm, last layer), PointPillarScatter ----

class PFNLayer(nn.Module):
    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.linear = nn.Linear(in_channels, out_channels, bias=False)
        self.norm = nn.BatchNorm1d(out_channels, eps=1e-3, momentum=0.01)

    def forward(self, points):  # (P, N, D) -> (P, C)
        x = self.linear(points)
        # Statistics over all P * N slots, padding included.
        x = self.norm(x.permute(0, 2, 1)).permute(0, 2, 1)
        x = F.relu(x)
        return torch.max(x, dim=1)[0]


class PillarVFE(nn.Module):
    def __init__(self, channels):
        super().__init__()
        self.pfn_layers = nn.ModuleList([PFNLayer(POINT_FEATURES, channels)])

    def forward(self, points):
        return self.pfn_layers[0](points)


def scatter(features, cells, batch, height, width):
    """PointPillarScatter: features (P, C), cells (P, 3: sample, iy, ix) -> (B, C, H, W)."""
    channels = features.shape[1]
    canvases = []
    for b in range(batch):
        canvas = features.new_zeros(channels, height * width)
        mine = cells[:, 0] == b
        index = cells[mine, 1] * width + cells[mine, 2]
        canvas[:, index] = features[mine].t()
        canvases.append(canvas.view(channels, height, width))
    return torch.stack(canvases)


# ---- the occupancy stream: Conv3x3 (no bias) -> BatchNorm (eps 1e-3, momentum 0.01) -> ReLU ----

class OccupancyStream(nn.Module):
    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False)
        self.norm = nn.BatchNorm2d(out_channels, eps=1e-3, momentum=0.01)

    def forward(self, x):
        return F.relu(self.norm(self.conv(x)))


# ---- milesial's U-Net parts (the 2020 version the authors used: convolutions with bias) ----

class DoubleConv(nn.Module):
    def __init__(self, in_channels, out_channels, mid_channels=None):
        super().__init__()
        if not mid_channels:
            mid_channels = out_channels
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
    """milesial's Up, with the skip's width given separately: without the input block the
    skip of the last Up is the input canvas (I channels), not b."""

    def __init__(self, in_channels, skip_channels, out_channels, bilinear):
        super().__init__()
        if bilinear:
            self.up = nn.Upsample(scale_factor=2, mode="bilinear", align_corners=True)
            cat = skip_channels + in_channels
            self.conv = DoubleConv(cat, out_channels, cat // 2)
        else:
            self.up = nn.ConvTranspose2d(in_channels, in_channels // 2, kernel_size=2, stride=2)
            self.conv = DoubleConv(skip_channels + in_channels // 2, out_channels)

    def forward(self, x1, x2):
        x1 = self.up(x1)
        diff_y = x2.size()[2] - x1.size()[2]
        diff_x = x2.size()[3] - x1.size()[3]
        x1 = F.pad(x1, [diff_x // 2, diff_x - diff_x // 2, diff_y // 2, diff_y - diff_y // 2])
        return self.conv(torch.cat([x2, x1], dim=1))


class OutConv(nn.Module):
    def __init__(self, in_channels, out_channels):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size=1)

    def forward(self, x):
        return self.conv(x)


class UNetWithoutInput(nn.Module):
    """milesial's UNet(n_channels, 12) minus `inc`, generalised to base width b and depth:
    down_i: w[i-1] -> w[i] with w[0] = I, w[i] = b * 2^i, the deepest divided by the factor
    (2 for bilinear, 1 for transposed); up_j to level l = depth - j: out b * 2^l / factor,
    b at level 0."""

    def __init__(self, in_channels, base_width, depth, bilinear):
        super().__init__()
        self.depth = depth
        factor = 2 if bilinear else 1
        widths = [in_channels] + [base_width * 2 ** i for i in range(1, depth + 1)]
        widths[depth] //= factor
        for i in range(1, depth + 1):
            setattr(self, f"down{i}", Down(widths[i - 1], widths[i]))
        current = widths[depth]
        for j in range(1, depth + 1):
            level = depth - j
            out = base_width if level == 0 else base_width * 2 ** level // factor
            setattr(self, f"up{j}", Up(current, widths[level], out, bilinear))
            current = out
        self.outc = OutConv(current, NUM_CLASSES)

    def forward(self, x):
        levels = [x]
        for i in range(1, self.depth + 1):
            levels.append(getattr(self, f"down{i}")(levels[-1]))
        x = levels[self.depth]
        for j in range(1, self.depth + 1):
            x = getattr(self, f"up{j}")(x, levels[self.depth - j])
        return self.outc(x)


class PillarSegNet(nn.Module):
    """Input canvas [pillar features (C), occupancy stream (Q), grid map (6)] -> U-Net."""

    def __init__(self, v):
        super().__init__()
        self.v = v
        in_channels = 0
        if v["pillars"]:
            self.vfe = PillarVFE(v["C"])
            in_channels += v["C"]
        if v["occupancy"] != "none":
            self.occupancy = OccupancyStream(occupancy_input_channels(v), v["Q"])
            in_channels += v["Q"]
        if v["grid_map"]:
            in_channels += 6
        self.segmentation_head = UNetWithoutInput(in_channels, v["b"], v["depth"],
                                                  v["upsampling"] == "bilinear")

    def forward(self, inputs):
        v = self.v
        parts = []
        if v["pillars"]:
            features = self.vfe(inputs["pillar_points"])
            parts.append(scatter(features, inputs["pillar_cells"], v["B"], v["H"], v["W"]))
        if v["occupancy"] != "none":
            parts.append(self.occupancy(inputs["occupancy"]))
        if v["grid_map"]:
            parts.append(inputs["grid_map"])
        return self.segmentation_head(torch.cat(parts, dim=1))


def occupancy_input_channels(v):
    return 1 if v["occupancy"] == "2d" else v["Z"]


# ---- losses (DESIGN.md section 3), over the M labelled cells ----

def loss_fn(kind, logits, labels, coefficients):
    labelled = labels > 0
    m = labelled.sum()
    target = (labels - 1).clamp(min=0)
    if kind == "ce":
        # Softmax cross-entropy weighted by the true class's coefficient, mean over M.
        nll = -F.log_softmax(logits, dim=1).gather(1, target[:, None])[:, 0]
        return (coefficients[labels] * nll)[labelled].sum() / m
    # Sigmoid BCE on one-hot targets, channel k weighted by coefficient k + 1, mean over M x 12.
    one_hot = F.one_hot(target, NUM_CLASSES).permute(0, 3, 1, 2).to(logits.dtype)
    per_channel = F.binary_cross_entropy_with_logits(logits, one_hot, reduction="none")
    per_channel = per_channel * coefficients[1:][None, :, None, None]
    return per_channel.sum(dim=1)[labelled].sum() / (m * NUM_CLASSES)


# ---- random weights and inputs ----

def randomise_weights(model, rng):
    """PyTorch's default initialisation for the convolutions and linear layers (from the
    seeded global generator), random BatchNorm affine parameters and running statistics so that
    none of them is the identity, and a non-zero counter."""
    def assign(tensor, values):
        with torch.no_grad():
            tensor.copy_(torch.from_numpy(values.astype(np.float32)))

    for module in model.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm):
            c = module.num_features
            assign(module.weight, rng.uniform(0.5, 1.5, c))
            assign(module.bias, rng.normal(0, 0.2, c))
            assign(module.running_mean, rng.normal(0, 0.3, c))
            assign(module.running_var, rng.uniform(0.5, 2.0, c))
            module.num_batches_tracked.fill_(int(rng.integers(0, 100)))


def random_inputs(v, rng):
    """Pillars over distinct cells of each sample (about a third of the cells), listed in a
    shuffled order across samples; 1..N points each, padding slots zero; occupancy and grid-map
    layers; labels with about 20% unlabelled cells; a distinct coefficient per class."""
    B, H, W, N = v["B"], v["H"], v["W"], v["N"]
    inputs = {}
    if v["pillars"]:
        cells = []
        for b in range(B):
            chosen = rng.choice(H * W, size=H * W // 3, replace=False)
            cells += [(b, int(c) // W, int(c) % W) for c in chosen]
        cells = np.array(cells, dtype=np.int64)[rng.permutation(len(cells))]
        points = np.zeros((len(cells), N, POINT_FEATURES), dtype=np.float32)
        counts = rng.integers(1, N + 1, size=len(cells))
        counts[0], counts[1] = 1, N  # both extremes, whatever the draw
        for p, n in enumerate(counts):
            points[p, :n] = rng.normal(0, 1, (n, POINT_FEATURES))
        inputs["pillar_points"] = points
        inputs["pillar_cells"] = cells
    if v["occupancy"] == "2d":  # log(1 + ray count)
        inputs["occupancy"] = np.log1p(rng.integers(0, 20, (B, 1, H, W))).astype(np.float32)
    elif v["occupancy"] == "3d":  # occupancy probabilities
        inputs["occupancy"] = rng.uniform(0, 1, (B, v["Z"], H, W)).astype(np.float32)
    if v["grid_map"]:
        inputs["grid_map"] = rng.normal(0, 1, (B, 6, H, W)).astype(np.float32)
    labels = rng.integers(1, NUM_CLASSES + 1, (B, H, W))
    labels[rng.uniform(0, 1, (B, H, W)) < 0.2] = 0
    inputs["labels"] = labels.astype(np.int64)
    # Class 0's coefficient is non-zero on purpose: unlabelled cells must be ignored anyway.
    coefficients = np.concatenate([[4.0], rng.permutation(np.linspace(0.5, 3.0, NUM_CLASSES))])
    inputs["coefficients"] = coefficients.astype(np.float32)
    return inputs


# ---- safetensors writer ----

def write_safetensors(path, tensors, metadata):
    """tensors: name -> numpy array (float32 or int64). Layout as the engine's writer: I64
    first, then F32, by name within a dtype, so every tensor is aligned to its element size."""
    dtype_names = {np.dtype(np.float32): "F32", np.dtype(np.int64): "I64"}
    order = sorted(tensors, key=lambda name: (tensors[name].dtype != np.int64, name))
    header = {"__metadata__": metadata} if metadata else {}
    chunks, offset = [], 0
    for name in order:
        array = np.asarray(tensors[name])  # keeps shape () (ascontiguousarray would make it (1))
        data = array.astype(array.dtype.newbyteorder("<"), copy=False).tobytes(order="C")
        header[name] = {"dtype": dtype_names[array.dtype], "shape": list(array.shape),
                        "data_offsets": [offset, offset + len(data)]}
        chunks.append(data)
        offset += len(data)
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * ((8 - (8 + len(text)) % 8) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(text)))
        f.write(text)
        for data in chunks:
            f.write(data)


def state_arrays(model, prefix):
    out = {}
    for name, value in model.state_dict().items():
        if name.endswith("num_batches_tracked"):
            out[prefix + name] = np.array(int(value), dtype=np.int64)
        else:
            out[prefix + name] = value.detach().to(torch.float32).numpy().copy()
    return out


def config_yaml(v):
    """The variant as the engine's YAML config: cells of 1 x 1 and voxel layers 1 high, so the
    ranges are the grid's W, H and Z exactly."""
    def flag(x):
        return "true" if x else "false"

    return (f"grid: {{x: [0, {v['W']}], y: [0, {v['H']}], z: [0, {v['Z']}], "
            f"cell: 1, voxel_z: 1}}\n"
            f"model: {{max_points_per_pillar: {v['N']}, pillars: {flag(v['pillars'])}, "
            f"pillar_channels: {v['C']}, occupancy: {v['occupancy']}, "
            f"occupancy_channels: {v['Q']}, grid_map: {flag(v['grid_map'])}, "
            f"base_width: {v['b']}, depth: {v['depth']}, upsampling: {v['upsampling']}}}\n")


def make(v, seed, path, weights_only_path):
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = PillarSegNet(v)
    randomise_weights(model, rng)
    inputs = random_inputs(v, rng)
    tensors = state_arrays(model, "param.")
    # The same weights as a PyTorch user exports them: the state_dict alone, no metadata (what
    # safetensors.torch.save_file(model.state_dict(), path) writes), which the engine opens
    # without a config (the architecture from the tensor shapes).
    write_safetensors(weights_only_path, state_arrays(model, ""), None)
    for key, value in inputs.items():
        tensors["input." + key] = value

    model.double()
    model.train()
    torch_inputs = {k: torch.from_numpy(a) for k, a in inputs.items()}
    torch_inputs = {k: t.double() if t.is_floating_point() else t for k, t in torch_inputs.items()}
    labels, coefficients = torch_inputs["labels"], torch_inputs["coefficients"]
    optimiser = torch.optim.AdamW(model.parameters(), lr=ADAM["lr"],
                                  betas=(ADAM["beta1"], ADAM["beta2"]), eps=ADAM["eps"],
                                  weight_decay=ADAM["weight_decay"])

    logits = model(torch_inputs)
    loss = loss_fn(v["loss"], logits, labels, coefficients)
    optimiser.zero_grad()
    loss.backward()
    tensors["out.logits_train"] = logits.detach().float().numpy()
    tensors["out.loss"] = np.array(loss.item(), dtype=np.float32)
    for name, p in model.named_parameters():
        tensors["grad." + name] = p.grad.float().numpy().copy()
    buffers = {name for name, _ in model.named_buffers()}
    tensors.update({k: a for k, a in state_arrays(model, "out.buffer.").items()
                    if k[len("out.buffer."):] in buffers})

    model.eval()
    with torch.no_grad():
        tensors["out.logits_eval"] = model(torch_inputs).float().numpy()
    model.train()

    optimiser.step()
    optimiser.zero_grad()
    loss2 = loss_fn(v["loss"], model(torch_inputs), labels, coefficients)
    loss2.backward()
    optimiser.step()
    tensors["out.loss_step2"] = np.array(loss2.item(), dtype=np.float32)
    tensors.update(state_arrays(model, "after_adam."))
    for name, p in model.named_parameters():
        state = optimiser.state[p]
        tensors["adam_m." + name] = state["exp_avg"].float().numpy().copy()
        tensors["adam_v." + name] = state["exp_avg_sq"].float().numpy().copy()

    metadata = {"config": config_yaml(v), "loss": v["loss"], "adam_steps": str(ADAM_STEPS),
                "generator": "tests/golden/make_golden.py", "torch": torch.__version__}
    metadata.update({k: repr(x) for k, x in ADAM.items()})
    write_safetensors(path, tensors, metadata)
    size = path.stat().st_size
    print(f"{path.name}: {len(tensors)} tensors, {size} bytes, loss {loss.item():.6f}")
    assert size < 1 << 20, "golden files must stay well under 1 MB"


# Odd grid sides so that max-pooling floors and every Up pads (asymmetrically where the
# difference is 1); depth 3 on 13 rows reaches a 1-row level, where bilinear upsampling
# has a single source row.
VARIANTS = {
    "pillars_bilinear_ce": dict(pillars=True, occupancy="none", grid_map=False,
                                upsampling="bilinear", loss="ce", W=23, H=13, depth=3),
    "pillars_occ2d_bilinear_bce": dict(pillars=True, occupancy="2d", grid_map=False,
                                       upsampling="bilinear", loss="bce", W=19, H=14, depth=2),
    "pillars_occ3d_transposed_ce": dict(pillars=True, occupancy="3d", grid_map=False,
                                        upsampling="transposed", loss="ce", W=21, H=11, depth=2),
    "gridmap_bilinear_bce": dict(pillars=False, occupancy="none", grid_map=True,
                                 upsampling="bilinear", loss="bce", W=17, H=10, depth=2),
}
COMMON = dict(B=2, Z=4, N=3, C=4, Q=3, b=4)


def main():
    torch.set_num_threads(1)  # one summation order: the files do not depend on the machine
    here = pathlib.Path(__file__).resolve().parent
    for seed, (name, variant) in enumerate(VARIANTS.items(), start=1):
        make({**COMMON, **variant}, seed, here / f"{name}.safetensors",
             here / f"weights_only_{name}.safetensors")


if __name__ == "__main__":
    main()
