#!/usr/bin/env bash
# The command line end to end on a tiny simulated data set: pillarseg infer over one scan, a
# directory and several files (the same label maps), --device emu for infer, bench, eval and
# train (training's first losses those of the CPU; in bf16 close to them), --precision, bench
# --save-canvas (the PFN's channels against one computed in the test), plot (the
# PNGs of a run with and without validation), errors that name the argument, and sizes refused
# before allocating (a low PILLARSEG_MEMORY_LIMIT, a grid beyond the 32-bit cell indices).
# Usage: tests/cli_test.sh PILLARSEG_BINARY WORK_DIR
set -euo pipefail
bin=$1 work=$2
rm -rf "$work"
mkdir -p "$work"
fail() { echo "cli_test: $*"; exit 1; }
run() { "$bin" --threads 2 "$@"; }

run simulate --out "$work/data" --sequences 1 --scans 3 --seed 9 --points-per-scan 30000 > /dev/null 2>&1
cat > "$work/tiny.yaml" <<'YAML'
grid: {x: [-20.0, 20.0], y: [-10.0, 10.0], z: [-2.5, 1.5], cell: 0.4, voxel_z: 0.2}
model: {max_points_per_pillar: 8, pillar_channels: 8, occupancy: 2d, occupancy_channels: 4, base_width: 8, depth: 2}
train: {epochs: 1, batch_size: 2, seed: 1, sequences: [0]}
eval: {sequences: [0]}
YAML
run train --data "$work/data" --config "$work/tiny.yaml" --out "$work/cpu" > /dev/null 2>&1
run train --data "$work/data" --config "$work/tiny.yaml" --out "$work/emu" --device emu > /dev/null 2>&1
run train --data "$work/data" --config "$work/tiny.yaml" --out "$work/emu_bf16" --device emu --precision bf16 \
  > "$work/emu_bf16.log" 2>&1 || { cat "$work/emu_bf16.log"; fail "train --device emu --precision bf16 failed"; }
grep -q 'precision bf16' "$work/emu_bf16.log" || fail "train --precision bf16: precision not logged"
first_loss() { grep -m1 '"type": "step"' "$1/metrics.jsonl" | sed 's/.*"loss": \([0-9.]*\).*/\1/'; }
python3 - "$(first_loss "$work/cpu")" "$(first_loss "$work/emu")" "$(first_loss "$work/emu_bf16")" <<'PY' ||
import sys
cpu, emu, bf16 = map(float, sys.argv[1:])
assert abs(cpu - emu) <= 1e-4 * abs(cpu), ("emu", cpu, emu)
assert abs(cpu - bf16) <= 2e-2 * abs(cpu), ("bf16", cpu, bf16)
print(f"cli_test: first training loss cpu {cpu}, emu {emu}, emu bf16 {bf16}")
PY
  fail "training on emu: first loss differs from the CPU's"
# The event file, read back by TensorBoard itself where it is installed.
python3 - "$work/cpu" <<'PY' || fail "TensorBoard does not read the event file as metrics.jsonl says"
import json, sys
try:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
except ImportError:
    print("cli_test: TensorBoard check skipped: the tensorboard Python package is not installed")
    sys.exit(0)
run = sys.argv[1]
acc = EventAccumulator(run)
acc.Reload()
got = [(e.step, e.value) for e in acc.Scalars("train/loss")]
want = [(r["step"], r["loss"]) for r in map(json.loads, open(run + "/metrics.jsonl")) if r["type"] == "step"]
assert [s for s, _ in got] == [s for s, _ in want], (got, want)
assert all(abs(a - b) <= 1e-5 * abs(b) + 1e-6 for (_, a), (_, b) in zip(got, want)), (got, want)
print(f"cli_test: TensorBoard reads {len(got)} train/loss scalars, those of metrics.jsonl")
PY
weights=$work/cpu/checkpoint.safetensors
velodyne=$work/data/sequences/00/velodyne

# pillarseg plot: a run validated after each of its 2 epochs gives all six charts; the CPU run above
# (no validation) the three training ones. Each a whole PNG: signature, chunk CRCs, the pixel rows.
sed -e 's/epochs: 1,/epochs: 2,/' -e 's/eval: {sequences: \[0\]}/eval: {sequences: [0], every_epochs: 1}/' \
  "$work/tiny.yaml" > "$work/tiny_eval.yaml"
grep -q 'every_epochs: 1' "$work/tiny_eval.yaml" || fail "tiny_eval.yaml: the sed did not add eval.every_epochs"
run train --data "$work/data" --config "$work/tiny_eval.yaml" --out "$work/eval_run" > "$work/eval_run.log" 2>&1 ||
  { cat "$work/eval_run.log"; fail "train with eval.every_epochs failed"; }
[[ $(grep -c '"type": "eval"' "$work/eval_run/metrics.jsonl") == 2 ]] || fail "train: expected 2 eval lines"
check_pngs() {
  python3 - "$@" <<'PY'
import struct, sys, zlib
for path in sys.argv[1:]:
    data = open(path, "rb").read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path}: no PNG signature"
    pos, idat, kinds = 8, b"", []
    while pos < len(data):
        n, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + n]
        assert struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])[0] == zlib.crc32(kind + body), f"{path}: bad CRC"
        if kind == b"IHDR":
            width, height, depth, colour = struct.unpack(">IIBB", body[:10])
        if kind == b"IDAT":
            idat += body
        kinds.append(kind)
        pos += 12 + n
    assert kinds[0] == b"IHDR" and kinds[-1] == b"IEND", f"{path}: chunks {kinds}"
    assert (depth, colour) == (8, 2) and width >= 200 and height >= 150, f"{path}: {width}x{height}"
    assert len(zlib.decompress(idat)) == height * (1 + 3 * width), f"{path}: pixel data size"
PY
}
plots=(loss lr grad_norm val_miou val_iou_per_class confusion)
run plot "$work/eval_run" > "$work/plot.log" 2>&1 || { cat "$work/plot.log"; fail "plot failed"; }
grep -q "wrote loss.png, lr.png, grad_norm.png, val_miou.png, val_iou_per_class.png, confusion.png in $work/eval_run/plots" \
  "$work/plot.log" || fail "plot: '$(cat "$work/plot.log")' does not list the six files"
pngs=()
for name in "${plots[@]}"; do pngs+=("$work/eval_run/plots/$name.png"); done
check_pngs "${pngs[@]}" || fail "plot: not six valid PNGs in $work/eval_run/plots"
[[ $(ls "$work/eval_run/plots" | wc -l) == 6 ]] || fail "plot: expected exactly six files in $work/eval_run/plots"
run plot "$work/cpu" --out "$work/cpu_plots" > "$work/plot_cpu.log" 2>&1 || { cat "$work/plot_cpu.log"; fail "plot --out failed"; }
grep -q "skipped val_miou.png, val_iou_per_class.png, confusion.png (no eval lines" "$work/plot_cpu.log" ||
  fail "plot of a run without validation: '$(cat "$work/plot_cpu.log")' does not say what it skipped and why"
check_pngs "$work"/cpu_plots/{loss,lr,grad_norm}.png || fail "plot --out: not three valid PNGs in $work/cpu_plots"
[[ ! -e $work/cpu_plots/val_miou.png && ! -e $work/cpu/plots ]] || fail "plot --out: files outside --out, or val_miou.png"
echo "cli_test: plot wrote six valid PNGs for a validated run, three for one without validation"

run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/one" > /dev/null
run infer --weights "$weights" --scan "$velodyne" --out "$work/dir" --no-png > "$work/dir.log" 2>&1
run infer --weights "$weights" --scan "$velodyne/000002.bin" "$velodyne/000001.bin" --out "$work/two" > /dev/null 2>&1
cmp "$work/one.u8" "$work/dir/000001.u8" || fail "infer over a directory: 000001.u8 differs from the single scan's"
cmp "$work/one.u8" "$work/two/000001.u8" || fail "infer over two files: 000001.u8 differs from the single scan's"
[[ -f $work/one.png && -f $work/two/000002.png && ! -e $work/dir/000001.png ]] || fail "infer: .png files (--no-png)"
[[ $(ls "$work/dir" | wc -l) == 3 ]] || fail "infer over a directory: expected 3 label maps in $work/dir"
grep -q 'scans/s end to end' "$work/dir.log" || fail "infer over a directory: no throughput line"
# Other point formats (docs/formats.md): scan 1 as .npy, as a nuScenes .pcd.bin, and as .npy under
# another name with --format give its label map; KITTI records named .npy are refused; the input
# mapping's identity as 16 numbers changes nothing, --no-reflectance is the scan with reflectance 0.
python3 - "$velodyne/000001.bin" "$work/formats" <<'PY'
import os, struct, sys
records, out = open(sys.argv[1], "rb").read(), sys.argv[2]
os.makedirs(out)
n = len(records) // 16
text = "{'descr': '<f4', 'fortran_order': False, 'shape': (%d, 4), }" % n
text += " " * ((64 - (10 + len(text) + 1) % 64) % 64) + "\n"
npy = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text.encode() + records
points = [struct.unpack_from("<4f", records, 16 * i) for i in range(n)]
files = {"scan.npy": npy, "scan.data": npy, "records.npy": records,
         "scan.pcd.bin": b"".join(struct.pack("<5f", *p, 0.0) for p in points),
         "zero_r.bin": b"".join(struct.pack("<4f", *p[:3], 0.0) for p in points)}
for name, data in files.items():
    open(os.path.join(out, name), "wb").write(data)
PY
formats=$work/formats
run infer --weights "$weights" --scan "$formats/scan.npy" --out "$formats/npy" --no-png > /dev/null
run infer --weights "$weights" --scan "$formats/scan.data" --format npy --out "$formats/data" --no-png > /dev/null
run infer --weights "$weights" --scan "$formats/scan.pcd.bin" --out "$formats/nuscenes" --no-png > /dev/null
run infer --weights "$weights" --scan "$formats/scan.npy" --transform "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1" \
  --out "$formats/identity" --no-png > /dev/null 2>&1
for f in npy data nuscenes identity; do
  cmp "$work/one.u8" "$formats/$f.u8" || fail "infer of scan 1 as $f: the label map differs from the .bin's"
done
run infer --weights "$weights" --scan "$velodyne/000001.bin" --no-reflectance --out "$formats/none" --no-png \
  > "$formats/none.log" 2>&1
grep -q 'input mapping: reflectance none (0)' "$formats/none.log" || fail "infer --no-reflectance: no mapping line"
run infer --weights "$weights" --scan "$formats/zero_r.bin" --out "$formats/zero_r" --no-png > /dev/null
cmp "$formats/none.u8" "$formats/zero_r.u8" || fail "infer --no-reflectance: not the map of the scan with reflectance 0"
message=$(run infer --weights "$weights" --scan "$formats/records.npy" --out "$formats/bad" 2>&1) &&
  fail "infer of KITTI records named .npy succeeded"
[[ $message == *"records.npy: not a NumPy .npy file"* ]] || fail "infer of KITTI records named .npy: '$message'"
echo "cli_test: infer read scan 1 as .npy, .pcd.bin and --format npy with the same label map"
# render: the four panels of a labelled scan, the tiny grid's 100 cells scaled by 10 to 1000 pixels
# on 12-pixel margins (the layout's pixels are checked in test_render).
run render --data "$work/data" --sequence 0 --scan 1 --weights "$weights" --out "$work/render.png" > "$work/render.log"
grep -q 'points, observability, prediction, sparse ground truth, 1024 x [0-9]* pixels (10 a cell)' "$work/render.log" ||
  fail "render: '$(cat "$work/render.log")' does not list four panels 1024 pixels wide at 10 a cell"
check_pngs "$work/render.png" || fail "render: $work/render.png is not a valid PNG"
python3 -c 'import struct, sys; w, h = struct.unpack(">II", open(sys.argv[1], "rb").read()[16:24]); sys.exit(w != 1024 or h < 4 * 500)' \
  "$work/render.png" || fail "render: $work/render.png is not 1024 pixels wide with four 500-pixel panels"
run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/emu_one" --device emu > /dev/null
run eval --data "$work/data" --weights "$weights" --mode sparse --device emu --report "$work/eval_emu.json" > /dev/null 2>&1
[[ -s $work/eval_emu.json ]] || fail "eval --device emu wrote no report"
# Test-time flips: --flips, else the config's eval.flips; named in the output and the report.
run eval --data "$work/data" --weights "$weights" --mode sparse --flips 4 --report "$work/eval_flips.json" \
  > "$work/eval_flips.log" 2>&1 || { cat "$work/eval_flips.log"; fail "eval --flips 4 failed"; }
grep -q "each scan's softmax the mean of 4 mirrored copies" "$work/eval_flips.log" || fail "eval --flips 4: not said"
grep -q '(4 flips)' "$work/eval_flips.json" || fail "eval --flips 4: the report does not say so"
sed 's/eval: {sequences: \[0\]}/eval: {sequences: [0], flips: 2}/' "$work/tiny.yaml" > "$work/tiny_flips.yaml"
run eval --data "$work/data" --weights "$weights" --config "$work/tiny_flips.yaml" --mode sparse \
  --report "$work/eval_flips2.json" > "$work/eval_flips2.log" 2>&1 || { cat "$work/eval_flips2.log"; fail "eval with eval.flips 2 failed"; }
grep -q '(2 flips)' "$work/eval_flips2.json" || fail "eval: the config's eval.flips 2 not used"
message=$(run bench --config "$work/tiny.yaml" --flips 2 --ops 2>&1) && fail "bench --flips 2 --ops succeeded"
[[ $message == *"--flips 2: --ops and --roofline time one pass"* ]] || fail "bench --flips 2 --ops: '$message'"

run bench --device emu --config "$work/tiny.yaml" --weights "$weights" --scan "$velodyne/000001.bin" --repeat 2 \
  > "$work/bench.log" 2>&1 || { cat "$work/bench.log"; fail "bench --device emu failed"; }
grep -q '^pillars ' "$work/bench.log" || fail "bench --device emu: no pillars stage (gather and decoration on the device)"
grep -q 'pillarize' "$work/bench.log" && fail "bench --device emu: a host pillarize stage"
grep -q '^bytes over the bus per scan' "$work/bench.log" || fail "bench --device emu: no bytes count"
grep -qE '^host cpu: .+, [0-9]+ threads; (BF16 on|no BF16 kernels)' "$work/bench.log" ||
  fail "bench: the host CPU and its BF16 kernels are not reported"

# bench --save-canvas: the U-Net's FP32 input canvas as .npy, (1, C + Q, H, W) float32 C order; its
# pillar channels against the PFN computed here in double from the checkpoint's weights and the
# scan's points (inference's point choice floor(k n / N), DESIGN.md section 1), zero where no
# point is; the occupancy stream's channels after a ReLU.
run bench --device cpu --config "$work/tiny.yaml" --weights "$weights" --scan "$velodyne/000001.bin" --repeat 1 \
  --save-canvas "$work/canvas.npy" > "$work/bench_canvas.log" 2>&1 ||
  { cat "$work/bench_canvas.log"; fail "bench --save-canvas failed"; }
python3 - "$work/canvas.npy" "$weights" "$velodyne/000001.bin" <<'PY' || fail "bench --save-canvas: the canvas is wrong"
import array, ast, json, math, struct, sys
raw = open(sys.argv[1], "rb").read()
assert raw[:8] == b"\x93NUMPY\x01\x00", raw[:8]
start = 10 + struct.unpack("<H", raw[8:10])[0]
assert start % 64 == 0, start
header = ast.literal_eval(raw[10:start].decode())
assert header == {"descr": "<f4", "fortran_order": False, "shape": (1, 12, 50, 100)}, header
canvas = array.array("f", raw[start:])
assert len(canvas) == 12 * 50 * 100, len(canvas)
ckpt = open(sys.argv[2], "rb").read()
meta_size = struct.unpack("<Q", ckpt[:8])[0]
meta = json.loads(ckpt[8:8 + meta_size])
def tensor(name):
    entry = meta[name]
    assert entry["dtype"] == "F32", entry
    begin, end = entry["data_offsets"]
    return list(array.array("f", ckpt[8 + meta_size + begin:8 + meta_size + end]))
pfn = "vfe.pfn_layers.0."
weight = tensor(pfn + "linear.weight")  # (8, 10)
gamma, beta, mean, var = (tensor(pfn + "norm." + k) for k in ("weight", "bias", "running_mean", "running_var"))
pts = array.array("f", open(sys.argv[3], "rb").read())
pillars = {}  # (iy, ix) -> points in file order
for i in range(0, len(pts), 4):
    x, y, z, r = pts[i:i + 4]
    if -20 <= x < 20 and -10 <= y < 10 and -2.5 <= z < 1.5:
        pillars.setdefault((math.floor((y + 10) / 0.4), math.floor((x + 20) / 0.4)), []).append((x, y, z, r))
plane, worst = 50 * 100, 0.0
for (iy, ix), points in pillars.items():
    n = len(points)
    kept = [points[k * n // 8] for k in range(8)] if n > 8 else points
    m = [sum(p[d] for p in kept) / len(kept) for d in range(3)]
    centre = (-20 + (ix + 0.5) * 0.4, -10 + (iy + 0.5) * 0.4, -0.5)
    rows = [list(p) + [p[d] - m[d] for d in range(3)] + [p[d] - centre[d] for d in range(3)] for p in kept]
    rows += [[0.0] * 10] * (8 - len(kept))
    for c in range(8):
        want = max(max(0.0, (sum(w * v for w, v in zip(weight[10 * c:10 * c + 10], row)) - mean[c]) /
                        math.sqrt(var[c] + 1e-3) * gamma[c] + beta[c]) for row in rows)
        got = canvas[c * plane + iy * 100 + ix]
        worst = max(worst, abs(got - want) / (1e-5 + 1e-5 * abs(want)))
assert worst <= 1, f"pillar channels: worst error {worst} tolerances (1e-5 + 1e-5 |ref|)"
empty = sum(1 for c in range(8) for cell in range(plane) if divmod(cell, 100) not in pillars and canvas[c * plane + cell] != 0)
assert empty == 0, f"{empty} pillar-channel values nonzero in cells without points"
occupancy = canvas[8 * plane:]
assert min(occupancy) >= 0 and max(occupancy) > 0 and all(math.isfinite(v) for v in occupancy), "occupancy channels"
print(f"cli_test: bench --save-canvas: {len(pillars)} pillars as computed here (worst {worst:.3f} of the tolerance)")
PY

# --precision bf16: the tensor-core convolutions on the emulation (a label map of the same size,
# mostly the FP32 one); on the CPU the AVX512_BF16 micro-kernel where the CPU has it, else one
# warning line and fp32; fp16 on the CPU always falls back; refused by train.
run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/bf16" --device emu --precision bf16 > /dev/null
cmp -s "$work/bf16.u8" "$work/emu_one.u8" && echo "cli_test: note: bf16 and fp32 label maps are identical"
[[ $(stat -c %s "$work/bf16.u8") == $(stat -c %s "$work/emu_one.u8") ]] || fail "infer --precision bf16: label map size"
message=$(run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/cpu_bf16" --precision bf16 2>&1)
if grep -qw avx512_bf16 /proc/cpuinfo && grep -qw avx512bw /proc/cpuinfo && grep -qw avx512vl /proc/cpuinfo; then
  [[ $message != *"running fp32"* ]] || fail "infer --precision bf16 on an AVX512_BF16 CPU fell back: '$message'"
  [[ $(stat -c %s "$work/cpu_bf16.u8") == $(stat -c %s "$work/one.u8") ]] || fail "infer --precision bf16 on the CPU: label map size"
else
  [[ $message == *"--precision bf16: the CPU's BF16 convolutions need AVX512_BF16: "*"running fp32"* ]] ||
    fail "infer --precision bf16 on the CPU: '$message'"
  cmp "$work/cpu_bf16.u8" "$work/one.u8" || fail "infer --precision bf16 on the CPU is not the fp32 label map"
fi
message=$(run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/cpu_fp16" --precision fp16 2>&1)
[[ $message == *"--precision fp16: the CPU backend has no FP16 convolutions"*"running fp32"* ]] ||
  fail "infer --precision fp16 on the CPU: '$message'"
cmp "$work/cpu_fp16.u8" "$work/one.u8" || fail "infer --precision fp16 on the CPU is not the fp32 label map"
run bench --device emu --precision bf16 --config "$work/tiny.yaml" --weights "$weights" --scan "$velodyne/000001.bin" \
  --repeat 1 --ops --roofline h200 > "$work/bench_bf16.log" 2>&1 ||
  { cat "$work/bench_bf16.log"; fail "bench --precision bf16 failed"; }
grep -q 'precision bf16' "$work/bench_bf16.log" || fail "bench --precision bf16: precision not reported"
# --ops: the tensor-core convolutions' row with the emulation's count of what they issued (at most
# 100% of it useful) and their bound on the H200; the network's roofline bound.
grep -qE '^conv forward bf16 \(tensor cores\) +[0-9]+ +[0-9.]+ +[0-9.]+ +[0-9.]+ +[0-9.]+ +[0-9.]+ +([0-9]|[1-9][0-9]|100)\.[0-9]% +[0-9.]+ +[0-9.]+ +(memory|compute)$' \
  "$work/bench_bf16.log" || { cat "$work/bench_bf16.log"; fail "bench --ops: no tensor-core row with counts and bound"; }
# INT8: calibrate the tiny model on the sequence, then infer with its scales; the calibrated file
# still loads as FP32 (the same label map as the original's); without scales --precision int8
# names the convolution and the command that writes them.
run calibrate --data "$work/data" --weights "$weights" --out "$work/int8.safetensors" --sequences 0 --scans 2 \
  > "$work/calibrate.log" 2>&1 || { cat "$work/calibrate.log"; fail "calibrate failed"; }
grep -qE '^calibrated [0-9]+ convolutions on 2 scans' "$work/calibrate.log" || fail "calibrate: $(cat "$work/calibrate.log")"
run infer --weights "$work/int8.safetensors" --scan "$velodyne/000001.bin" --out "$work/int8_fp32" > /dev/null 2>&1 ||
  fail "infer of the calibrated checkpoint in fp32 failed"
cmp "$work/int8_fp32.u8" "$work/one.u8" || fail "the calibrated checkpoint in fp32 is not the original's label map"
run infer --weights "$work/int8.safetensors" --scan "$velodyne/000001.bin" --out "$work/int8" --precision int8 \
  > "$work/int8.log" 2>&1 || { cat "$work/int8.log"; fail "infer --precision int8 failed"; }
[[ -s "$work/int8.u8" ]] || fail "infer --precision int8 wrote no label map"
if message=$(run infer --weights "$weights" --scan "$velodyne/000001.bin" --out "$work/int8_bad" --precision int8 2>&1); then
  fail "infer --precision int8 without calibrated scales succeeded"
fi
[[ $message == *"no input scale for the convolution"*"pillarseg calibrate"* ]] ||
  fail "infer --precision int8 without scales: '$message'"
# eval too, and on every CPU: also where INT8 falls back to FP32 (no VNNI), the scales are asked for.
if message=$(run eval --data "$work/data" --weights "$weights" --mode sparse --precision int8 \
             --report "$work/eval_int8_bad.json" 2>&1); then
  fail "eval --precision int8 without calibrated scales succeeded"
fi
[[ $message == *"no input scale for the convolutions"*"pillarseg calibrate"* && ! -e "$work/eval_int8_bad.json" ]] ||
  fail "eval --precision int8 without scales: '$message'"
# bench --precision int8 of weights without scales calibrates on the benched scan itself, also on
# a device that records its pipeline as a graph (the calibrating pass runs unrecorded); with
# --flips 2 the steady state replays the graph once per copy.
run bench --device emu --precision int8 --flips 2 --config "$work/tiny.yaml" --weights "$weights" \
  --scan "$velodyne/000001.bin" --repeat 1 > "$work/bench_int8.log" 2>&1 ||
  { cat "$work/bench_int8.log"; fail "bench --device emu --precision int8 failed"; }
grep -q 'calibrated on the benched scan itself' "$work/bench_int8.log" || fail "bench --precision int8: no calibration line"
grep -qE '^steady state \(upload, 2 graph replays, one per copy, download\): [0-9.]+ ms' "$work/bench_int8.log" ||
  fail "bench --flips 2: no steady state of two replays"
grep -qE '^int8 against fp32: arg-max agreement [0-9.]+%' "$work/bench_int8.log" ||
  fail "bench --precision int8: no agreement with fp32"
grep -qE '^roofline bound on h200 .*: [0-9.]+ ms for the network' "$work/bench_bf16.log" ||
  fail "bench --roofline h200: no bound for the network"
grep -qE '^training step on h200 \(batch 2, [1-9][0-9]* pillar rows, bf16 convolutions\): bound [0-9.]+ ms .* at least [0-9.]+ h on one' \
  "$work/bench_bf16.log" || fail "bench --roofline h200: no bound for a bf16 training step"

# Errors name the argument and exit 1.
expect_error() {
  local expected=$1
  shift
  set +e
  message=$(run "$@" 2>&1)
  local rc=$?
  set -e
  [[ $rc == 1 ]] || fail "'$*' exited $rc, expected 1: $message"
  [[ $message == *"$expected"* ]] || fail "'$*': '$message' does not say '$expected'"
}
# plot: no metrics.jsonl; a broken line (named by file:line); a log without steps: nothing written.
mkdir -p "$work/no_run" "$work/bad_run" "$work/stepless_run"
expect_error "$work/no_run/metrics.jsonl: no such file" plot "$work/no_run"
{ head -n 3 "$work/eval_run/metrics.jsonl"; echo '{"type": "step", "epoch": 1, "step": 4, "loss": nan}'; } \
  > "$work/bad_run/metrics.jsonl"
expect_error "$work/bad_run/metrics.jsonl:4: not valid JSON" plot "$work/bad_run"
grep -v '"type": "step"' "$work/eval_run/metrics.jsonl" > "$work/stepless_run/metrics.jsonl"
expect_error "$work/stepless_run/metrics.jsonl: no step lines" plot "$work/stepless_run"
[[ ! -e $work/no_run/plots && ! -e $work/bad_run/plots && ! -e $work/stepless_run/plots ]] ||
  fail "plot wrote a plots directory for a bad log"
expect_error "--roofline h300: unknown GPU; known: h200" bench --device emu --config "$work/tiny.yaml" --ops \
  --roofline h300
expect_error "--scan $work/none.bin: no such file" infer --weights "$weights" --scan "$work/none.bin" --out "$work/x"
expect_error "is a file" infer --weights "$weights" --scan "$velodyne" --out "$work/one.u8"
expect_error "train --precision bf16: backend cpu trains in fp32 only" train --data "$work/data" \
  --config "$work/tiny.yaml" --out "$work/bf16_run" --precision bf16
[[ ! -e "$work/bf16_run" ]] || fail "train --precision bf16 on the CPU left a run directory"
# A --device outside cpu, cuda, emu: the command line refuses it and names the option.
if message=$(run infer --weights "$weights" --scan "$velodyne" --out "$work/y" --device tpu 2>&1); then
  fail "--device tpu was accepted"
fi
[[ $message == *"--device"* ]] || fail "--device tpu: '$message' does not name --device"
# Sizes checked before allocating: training and inference beyond a (low) memory limit, before a
# run directory is made; a grid beyond the 32-bit cell indices, when the config is read.
PILLARSEG_MEMORY_LIMIT=1M \
  expect_error "training of PillarSegNet on a 100 x 50 grid of 0.4 m cells (batch 2) would need" \
  train --data "$work/data" --config "$work/tiny.yaml" --out "$work/big_run"
[[ ! -e "$work/big_run" ]] || fail "train beyond the memory limit left a run directory"
PILLARSEG_MEMORY_LIMIT=1M \
  expect_error "evaluation of PillarSegNet on a 100 x 50 grid of 0.4 m cells (batch 1) would need" \
  infer --weights "$weights" --scan "$velodyne/000000.bin" --out "$work/z"
sed 's/cell: 0.4/cell: 0.0001/' "$work/tiny.yaml" > "$work/fine.yaml"
expect_error "grid of 400000 x 200000 cells = 80000000000 overflows the 32-bit cell indices" \
  train --data "$work/data" --config "$work/fine.yaml" --out "$work/fine_run"
# The emulation's schedule (PILLARSEG_EMU_SCHEDULE): another order gives the same label map; a
# bad value fails the command with a message naming the variable.
PILLARSEG_EMU_SCHEDULE=random:5 run infer --weights "$weights" --scan "$velodyne/000000.bin" \
  --out "$work/emu_random" --device emu > /dev/null
run infer --weights "$weights" --scan "$velodyne/000000.bin" --out "$work/emu_forward" --device emu > /dev/null
cmp -s "$work/emu_random.u8" "$work/emu_forward.u8" || fail "--device emu: random:5 and forward label maps differ"
PILLARSEG_EMU_SCHEDULE=sideways expect_error "PILLARSEG_EMU_SCHEDULE='sideways': expected forward, reverse or random:SEED" \
  infer --weights "$weights" --scan "$velodyne/000000.bin" --out "$work/emu_bad" --device emu
echo "cli_test: infer (one scan, a directory, two files), --device emu (infer, eval, bench, train)," \
  "--precision, plot, errors and size checks pass"
