// Fuzz target: a checkpoint (engine/model/checkpoint.hpp) as `pillarseg eval`, `infer` and
// pillarseg_open read it: read_checkpoint (the safetensors file and its metadata: the run config,
// epoch, step, best mIoU and epoch), config_for (a weights-only file's architecture from its
// tensor shapes, engine/model/architecture.hpp) and load_weights into the tiny model
// (fuzz/tiny_model.yaml), with the optimiser moments when the file has them.
#include <cstddef>
#include <cstdint>
#include <memory>

#include "core/error.hpp"
#include "engine/backend/backend.hpp"
#include "engine/model/checkpoint.hpp"
#include "engine/model/pillarsegnet.hpp"
#include "engine/model/run_config.hpp"
#include "fuzz/fuzz_support.hpp"

namespace fuzz = pillarseg::fuzz;

namespace {

pillarseg::PillarSegNet& tiny_net() {
  static const pillarseg::RunConfig config =
      pillarseg::parse_run_config(fuzz::tiny_model_config(), "fuzz/tiny_model.yaml");
  static const std::unique_ptr<pillarseg::Backend> backend = pillarseg::make_cpu_backend();
  static pillarseg::PillarSegNet net(config.model, *backend, /*seed=*/11);
  return net;
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  fuzz::quiet_logs();
  tiny_net();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::filesystem::path path = fuzz::write_scratch("checkpoint.safetensors", data, size);
  try {
    const pillarseg::Checkpoint checkpoint = pillarseg::read_checkpoint(path);
    fuzz::check(checkpoint.state.best_miou < 0 ||
                    (checkpoint.state.best_miou >= 0 && checkpoint.state.best_miou <= 1),
                "best_miou is none or an mIoU");
    const pillarseg::RunConfig config = pillarseg::config_for(checkpoint, {});
    config.model.validate();
    pillarseg::load_weights(checkpoint, tiny_net(), checkpoint.has_optimizer);
  } catch (const pillarseg::Error&) {
  }
  return 0;
}
