// Small helpers shared by the subcommands.
#pragma once

#include <CLI/CLI.hpp>
#include <filesystem>
#include <string>

#include "core/error.hpp"
#include "engine/data/semantickitti.hpp"
#include "engine/pipeline/segmenter.hpp"

namespace pillarseg::cli {

// Index within the sequence of the scan whose point file is NNNNNN.<ext> for frame `frame`.
inline size_t scan_index(const Sequence& seq, int frame) {
  for (size_t i = 0; i < seq.size(); ++i)
    if (seq.frame(i) == frame) return i;
  PS_FAIL("--scan {}: no point file {:06}.* in {}", frame, frame, (seq.dir() / "velodyne").string());
}

// Checks that an output path has one of the given extensions (lower case, with the dot).
inline void require_extension(const std::filesystem::path& path, std::initializer_list<const char*> allowed,
                              const std::string& option) {
  std::string ext = path.extension().string();
  for (char& c : ext) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  for (const char* a : allowed)
    if (ext == a) return;
  std::string list;
  for (const char* a : allowed) list += (list.empty() ? "" : ", ") + std::string(a);
  PS_FAIL("{} {}: unsupported extension '{}' (expected {})", option, path.string(), ext, list);
}

// --device, --conv and --precision, the same on every command that runs the network (infer,
// render, eval, bench, train).
struct DeviceArgs {
  std::string device = "cpu", conv = "own", precision = "fp32";
  int cuda_device = 0;
};
inline void add_device_options(CLI::App* cmd, DeviceArgs& args) {
  cmd->add_option("--device", args.device,
                  "cpu; cuda (a GPU); emu (the CUDA backend on the CPU emulation: every kernel run "
                  "on the CPU, slow, for verification)")
      ->check(CLI::IsMember({"cpu", "cuda", "emu"}));
  cmd->add_option("--conv", args.conv,
                  "Conv2d with --device cuda: own (our kernels), cudnn or cublas (for comparison)")
      ->check(CLI::IsMember({"own", "cudnn", "cublas"}));
  cmd->add_option("--cuda-device", args.cuda_device, "the CUDA device ordinal with --device cuda")
      ->check(CLI::NonNegativeNumber);
  cmd->add_option("--precision", args.precision,
                  "the convolutions: fp32, or bf16 / fp16 (tensor cores on --device cuda, compute capability "
                  "8.0+, or emu; bf16 also on CPUs with AVX512_BF16; elsewhere one line says so and fp32 runs; "
                  "train: cuda or emu only, with FP32 master weights), or int8 (inference: the U-Net on INT8, "
                  "a checkpoint calibrated by pillarseg calibrate; CPUs with AVX512-VNNI, AMX-INT8 where "
                  "present, cuda/emu)")
      ->check(CLI::IsMember({"fp32", "bf16", "fp16", "int8"}));
}

// --flips on infer, render and bench (eval: its default is the config's eval.flips).
inline constexpr const char* kFlipsHelp =
    "test-time mirrors: the softmax averaged over 1, 2 (and y -> -y) or 4 (and x -> -x, and both) copies of "
    "each scan, that many passes; the grid must be symmetric about the sensor";
inline void add_flips_option(CLI::App* cmd, int& flips, const std::string& default_note = " (default 1)") {
  cmd->add_option("--flips", flips, kFlipsHelp + default_note)->check(CLI::IsMember({1, 2, 4}));
}

// The segmenter options of --device, --conv, --cuda-device and --precision.
inline SegmenterOptions segmenter_options(const DeviceArgs& args) {
  SegmenterOptions options;
  options.device = args.device;
  options.backend = {args.conv, args.cuda_device};
  options.precision = parse_precision(args.precision);
  return options;
}

}  // namespace pillarseg::cli
