#!/usr/bin/env python3
"""Resource usage of every CUDA kernel, from the ptxas output of an nvcc build with
--resource-usage (make kernel-report). Prints one row per kernel with its registers, static
shared memory, stack frame and spills on each architecture, and exits 1 if any kernel spills.

Usage: kernel_report.py BUILD_LOG [KERNEL_LIBRARY.a]
With cuobjdump on PATH, also prints its own listing of the library's kernels
(cuobjdump --dump-resource-usage); the CUDA 13 toolkit here ships without it.
"""
import re
import shutil
import subprocess
import sys
from collections import defaultdict

ENTRY = re.compile(r"Compiling entry function '([^']+)' for '(sm_\d+)'")
FRAME = re.compile(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads")
USED = re.compile(r"Used (\d+) registers")
SMEM = re.compile(r"(\d+) bytes smem")
PROPERTIES = re.compile(r"Function properties for (\S+)")


def demangle(names):
    if not names or shutil.which("c++filt") is None:
        return {n: n for n in names}
    out = subprocess.run(["c++filt"], input="\n".join(names), capture_output=True, text=True).stdout
    return dict(zip(names, out.splitlines()))


def short(signature):
    """pillarseg::cuda::conv2d_forward_kernel<64, 64>(...) -> conv2d_forward_kernel<64, 64>"""
    name = re.sub(r"^void ", "", signature.split("(")[0])
    name = re.sub(r"^pillarseg::cuda::(\(anonymous namespace\)::)?", "", name)
    return name.replace("pillarseg::cuda::", "")


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    kernels = defaultdict(dict)  # mangled name -> arch -> (regs, smem, stack, spill_st, spill_ld)
    # Spills of non-inlined device functions: (function, arch) -> (stack, spill_st, spill_ld).
    functions = {}
    current = None
    properties_of = None  # the function whose "Function properties" block is being read
    with open(sys.argv[1], errors="replace") as log:
        for line in log:
            m = ENTRY.search(line)
            if m:
                current = [m.group(1), m.group(2), 0, 0, 0, 0, 0]
                kernels[current[0]][current[1]] = current
                properties_of = None
                continue
            if current is None:
                continue
            m = PROPERTIES.search(line)
            if m:
                properties_of = m.group(1)
                continue
            m = FRAME.search(line)
            if m:
                frame = tuple(int(g) for g in m.groups())
                # ptxas lists a called function's frame after the kernel's: it must not
                # overwrite the kernel's numbers, and its spills are spills too.
                if properties_of in (None, current[0]):
                    current[4], current[5], current[6] = frame
                else:
                    functions[(properties_of, current[1])] = frame
                continue
            m = USED.search(line)
            if m:
                current[2] = int(m.group(1))
                s = SMEM.search(line)
                current[3] = int(s.group(1)) if s else 0
    if not kernels:
        sys.exit(f"{sys.argv[1]}: no ptxas resource lines (was the kernel library built with "
                 "-DPILLARSEG_CUDA_RESOURCE_USAGE=ON, from clean?)")
    names = demangle(sorted(kernels))
    archs = sorted({a for per in kernels.values() for a in per}, key=lambda a: int(a[3:]))
    print(f"{len(kernels)} kernels x {len(archs)} architectures ({', '.join(archs)})\n")
    print("| kernel | registers | static smem B | stack B | spills (store/load B) |")
    print("|---|---|---|---|---|")
    spilled = []
    for mangled in sorted(kernels, key=lambda n: short(names[n])):
        per = kernels[mangled]

        def column(i):
            values = [per[a][i] for a in archs if a in per]
            lo, hi = min(values), max(values)
            return str(lo) if lo == hi else f"{lo}-{hi}"

        spills = [(a, per[a][5], per[a][6]) for a in archs if a in per and (per[a][5] or per[a][6])]
        if spills:
            spilled.append(short(names[mangled]))
        spill_text = ", ".join(f"{a}: {st}/{ld}" for a, st, ld in spills) or "none"
        print(f"| {short(names[mangled])} | {column(2)} | {column(3)} | {column(4)} | {spill_text} |")
    if len(sys.argv) > 2 and shutil.which("cuobjdump"):
        print("\ncuobjdump --dump-resource-usage:")
        subprocess.run(["cuobjdump", "--dump-resource-usage", sys.argv[2]], check=False)
    function_names = demangle(sorted({f for f, _ in functions}))
    for (function, arch), (stack, st, ld) in sorted(functions.items()):
        if st or ld:
            spilled.append(f"{short(function_names[function])} ({arch}, called function)")
    if spilled:
        print(f"\n{len(spilled)} kernels or called functions spill registers: {', '.join(spilled)}")
        return 1
    print("\nno kernel spills registers")
    return 0


if __name__ == "__main__":
    sys.exit(main())
