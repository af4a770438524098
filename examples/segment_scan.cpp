// Segments one SemanticKITTI scan with the C++ API: segment_scan_cpp WEIGHTS SCAN.bin OUT.u8
// [DEVICE] writes the label map (as `pillarseg infer` writes PREFIX.u8), then segments the scan
// again on the same segmenter (the steady state: nothing allocated) and prints both times.
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <iterator>
#include <vector>

#include <pillarseg/pillarseg.hpp>

int main(int argc, char** argv) {
  if (argc < 4) {
    std::cerr << "usage: " << argv[0] << " WEIGHTS.safetensors SCAN.bin OUT.u8 [cpu|cuda|emu]\n";
    return 2;
  }
  std::ifstream in(argv[2], std::ios::binary);
  const std::vector<char> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  std::vector<float> points(bytes.size() / 16 * 4);
  std::copy(bytes.begin(), bytes.begin() + static_cast<std::ptrdiff_t>(points.size() * 4),
            reinterpret_cast<char*>(points.data()));
  try {
    pillarseg::Options options;
    if (argc > 4) options.device = argv[4];
    pillarseg::Segmenter segmenter(argv[1], options);
    using Clock = std::chrono::steady_clock;
    const auto t0 = Clock::now();
    const std::vector<std::uint8_t> labels = segmenter.segment(points);
    const auto t1 = Clock::now();
    segmenter.segment(points);
    const auto t2 = Clock::now();
    std::ofstream(argv[3], std::ios::binary)
        .write(reinterpret_cast<const char*>(labels.data()), static_cast<std::streamsize>(labels.size()));
    const auto ms = [](auto d) { return std::chrono::duration<double, std::milli>(d).count(); };
    std::cout << "pillarseg " << pillarseg::version() << " on " << segmenter.device() << ": "
              << points.size() / 4 << " points -> " << segmenter.width() << " x " << segmenter.height()
              << " cells; first scan " << ms(t1 - t0) << " ms, again " << ms(t2 - t1) << " ms\n";
  } catch (const pillarseg::Error& e) {
    std::cerr << e.what() << "\n";
    return 1;
  }
  return 0;
}
