# pillarseg: the two commands of the README, and a few more for developers.
#   make demo   simulate a small data set, build ground truth, train, evaluate, render PNGs
#   make table1 every row of the paper's Table I on the simulator at the small CPU size, the
#               paper's figures beside (scripts/table1.sh; TABLE1_OUT, TABLE1_EPOCHS, TABLE1_SCANS)
#   make test   build everything and run the test suite (CTest)
#   make fuzz   each reader's libFuzzer target, ASan + UBSan, FUZZ_SECONDS each (scripts/fuzz.sh)
BUILD ?= build
JOBS ?= $(shell nproc)
CMAKE_FLAGS ?=
DEMO_OUT ?= demo_out
TABLE1_OUT ?= table1_out

.PHONY: all deps configure build test demo table1 bench asan kernel-report gpu-bundle clean

all: build

deps:
	@scripts/install-deps.sh

configure: deps
	@cmake -S . -B $(BUILD) -DCMAKE_BUILD_TYPE=Release $(CMAKE_FLAGS) >/dev/null

build: configure
	@cmake --build $(BUILD) -j $(JOBS)

test: build
	@ctest --test-dir $(BUILD) --output-on-failure -j $(JOBS)

demo: build
	@scripts/demo.sh $(BUILD)/pillarseg $(DEMO_OUT)

table1: build
	@scripts/table1.sh $(BUILD)/pillarseg $(TABLE1_OUT)

bench: build
	@for b in $(BUILD)/bench/bench_*; do echo "== $$b"; $$b --benchmark_min_time=0.2; done

# AddressSanitizer + UndefinedBehaviorSanitizer build of the whole test suite (the kernels on the
# emulation; the nvcc targets are not built).
asan: deps
	@cmake -S . -B build-asan -DCMAKE_BUILD_TYPE=RelWithDebInfo -DPILLARSEG_SANITIZE=ON -DPILLARSEG_BENCH=OFF -DPILLARSEG_CUDA=OFF >/dev/null
	@cmake --build build-asan -j $(JOBS)
	@ctest --test-dir build-asan --output-on-failure -j $(JOBS)

# The libFuzzer targets of fuzz/ (clang 14, build-fuzz), each for FUZZ_SECONDS (default 600); a
# crash's input goes to fuzz/findings/ and the target fails.
.PHONY: fuzz
fuzz: deps
	@FUZZ_SECONDS=$(or $(FUZZ_SECONDS),600) JOBS=$(JOBS) scripts/fuzz.sh

# Every CUDA kernel with its registers, shared memory, stack and spills per architecture, from
# ptxas (a separate build of the kernel library; needs nvcc). Fails if a kernel spills. Without
# cuobjdump (the CUDA 13 toolkit here has none) it then lists every kernel of every architecture
# from the library's own cubins (scripts/cubin_list.py, unit-tested first) and fails if those
# differ from ptxas's kernels, registers or stack frames.
kernel-report: deps
	@cmake -S . -B build-kernels -DCMAKE_BUILD_TYPE=Release -DPILLARSEG_CUDA_RESOURCE_USAGE=ON >/dev/null
	@cmake --build build-kernels --target pillarseg_kernels_cuda --clean-first -j $(JOBS) > build-kernels/resource-usage.log 2>&1 \
	  || { tail -20 build-kernels/resource-usage.log; exit 1; }
	@PILLARSEG_KERNEL_LIBRARY=build-kernels/kernels/libpillarseg_kernels_cuda.a python3 scripts/test_cubin_list.py \
	  > build-kernels/cubin-list-test.log 2>&1 || { cat build-kernels/cubin-list-test.log; exit 1; }
	@python3 scripts/kernel_report.py build-kernels/resource-usage.log build-kernels/kernels/libpillarseg_kernels_cuda.a

# The GPU check in one call: build-gpu/bundle (build-gpu/bundle.tar.gz, at most 40 MiB, is what travels) holds pillarseg, every *_gpu test,
# the kernel benchmarks and the libraries a bare CUDA machine lacks, built here for GPU_ARCH only,
# and run.sh, which runs all of it there in at most 8 minutes (README: "On a GPU machine").
GPU_ARCH ?= 90
gpu-bundle: deps
	@cmake -S . -B build-gpu -DCMAKE_BUILD_TYPE=Release -DCMAKE_CUDA_ARCHITECTURES=$(GPU_ARCH) \
	  -DPILLARSEG_ARCH=x86-64-v3 -DPILLARSEG_BENCH=ON -DPILLARSEG_TESTS=ON >/dev/null
	@cmake --build build-gpu -j $(JOBS) --target pillarseg bench_kernels_conv bench_kernels_pipeline bench_kernels_reference \
	  $$(cmake --build build-gpu --target help | sed -n 's/^\.\.\. \(test_.*_gpu\)$$/\1/p')
	@scripts/gpu_bundle.sh pack build-gpu build-gpu/bundle
	@scripts/gpu_bundle.sh check build-gpu/bundle

clean:
	rm -rf $(BUILD) build-asan build-kernels build-gpu
