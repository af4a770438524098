// Fixtures of the library tests (test_library): checkpoints and scans made with the engine, named
// by plain paths so that a translation unit that includes only the public headers can use them.
#pragma once

#include <string>
#include <vector>

namespace pillarseg_test {

// A checkpoint of the tiny 2D-occupancy model with random weights (seeded), written once.
const std::string& tiny_checkpoint();
// A simulated scan on that model's grid: x, y, z, r per point.
std::vector<float> tiny_scan(int points, unsigned seed);

}  // namespace pillarseg_test
