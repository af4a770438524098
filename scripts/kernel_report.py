#!/usr/bin/env python3
"""Resource usage of every CUDA kernel, from the ptxas output of an nvcc build with
--resource-usage (make kernel-report). Prints one row per kernel with its registers, static
shared memory, stack frame and spills on each architecture, and exits 1 if any kernel spills.

Usage: kernel_report.py BUILD_LOG [KERNEL_LIBRARY.a]
With cuobjdump on PATH, also prints its own listing of the library's kernels
(cuobjdump --dump-resource-usage). The CUDA 13 toolkit here ships without it: then the library's
cubins are read directly (cubin_list.py) and every kernel on every architecture is listed from
the binary and checked against the log: the same kernels on each architecture both ways, the same
registers and stack frame. Exits 2 on a mismatch (1 stays "a kernel spills").
"""
import re
import shutil
import subprocess
import sys
from collections import defaultdict

import cubin_list

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
    """pillarseg::cuda::gpu::(anonymous namespace)::conv2d_forward_kernel<64, 64>(...)
    -> conv2d_forward_kernel<64, 64> (gpu / emu: the inline namespace of the build)"""
    signature = signature.replace("(anonymous namespace)::", "")
    signature = re.sub(r"pillarseg::cuda::((gpu|emu)::)?", "", signature)
    depth = 0  # the parameter list's "(" is the first outside the template arguments
    for i, c in enumerate(signature):
        depth += {"<": 1, ">": -1}.get(c, 0)
        if c == "(" and depth == 0:
            signature = signature[:i]
            break
    return re.sub(r"^void ", "", signature)


def check_binary(library, kernels, names):
    """Lists the kernels of `library` (the static library the log was built with) per architecture
    from its cubins and compares them with the ptxas log's `kernels` (mangled -> arch -> row).
    Returns the number of mismatches (kernel missing on one side, registers or frame differ)."""
    try:
        with open(library, "rb") as f:
            listing = cubin_list.list_library(f.read())
    except (OSError, cubin_list.FormatError) as error:
        print(f"\ncannot list the kernels of {library}: {error}")
        return 1
    print(f"\nkernels in {library} (read from its cubins; cuobjdump is not installed):")
    ptx_storage = sorted({compression or "uncompressed"
                          for _, _, compression in listing.ptx_entries})
    if ptx_storage:
        print(f"  {len(listing.ptx_entries)} PTX entries ({', '.join(ptx_storage)}), not read: "
              "the cubins carry the compiled kernels")
    for problem in listing.problems:
        print(f"  cannot read: {problem}")
    logged = defaultdict(dict)  # arch -> mangled -> ptxas row
    for mangled, per in kernels.items():
        for arch, row in per.items():
            logged[arch][mangled] = row
    binary_names = demangle(sorted({m for per in listing.kernels.values() for m in per}))
    binary_archs = sorted(listing.kernels, key=lambda a: int(a[3:]))
    print("\n| kernel (library) | " + " | ".join(binary_archs) + " |")
    print("|---|" + "---|" * len(binary_archs))
    for mangled in sorted(binary_names, key=lambda n: short(binary_names[n])):
        cells = []
        for arch in binary_archs:
            kernel = listing.kernels[arch].get(mangled)
            cells.append("absent" if kernel is None else
                         f"{kernel.registers} reg, {kernel.shared_bytes} B smem, "
                         f"{kernel.frame_bytes} B frame")
        print(f"| {short(binary_names[mangled])} | " + " | ".join(cells) + " |")
    print()
    mismatches = len(listing.problems)
    for arch in sorted(set(logged) | set(listing.kernels), key=lambda a: int(a[3:])):
        in_binary = listing.kernels.get(arch, {})
        in_log = logged.get(arch, {})
        agree = 0
        smem_offsets = defaultdict(int)  # binary .nv.shared size - ptxas smem -> kernel count
        for mangled in sorted(set(in_binary) | set(in_log)):
            label = short(names.get(mangled) or binary_names[mangled])
            if mangled not in in_binary:
                print(f"  MISMATCH {arch}: {label} is in the ptxas log, not in the library")
            elif mangled not in in_log:
                print(f"  MISMATCH {arch}: {label} is in the library, not in the ptxas log")
            else:
                kernel, row = in_binary[mangled], in_log[mangled]
                if (kernel.registers, kernel.frame_bytes) != (row[2], row[4]):
                    print(f"  MISMATCH {arch}: {label}: library {kernel.registers} registers, "
                          f"{kernel.frame_bytes} B frame; ptxas {row[2]} registers, "
                          f"{row[4]} B frame")
                else:
                    agree += 1
                    if row[3] or kernel.shared_bytes:
                        smem_offsets[kernel.shared_bytes - row[3]] += 1
                    continue
            mismatches += 1
        # Informational, not checked: in the sm_90 cubins of our build (the only ones with a
        # .nv.shared.reserved.0 section) each .nv.shared.<kernel> is 1024 B over ptxas's "bytes
        # smem", the reserved shared memory placed ahead of the kernel's own; the cubin records
        # that size nowhere else, so the difference is shown rather than assumed.
        smem = ", ".join(f"+{d} B for {n}" if d else f"equal for {n}"
                         for d, n in sorted(smem_offsets.items())) or "no kernel uses any"
        print(f"  {arch}: {len(in_binary)} kernels in the library, {len(in_log)} in the log, "
              f"{agree} with equal registers and stack frame; static smem vs ptxas: {smem}")
    return mismatches


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
    mismatches = 0
    if len(sys.argv) > 2 and shutil.which("cuobjdump"):
        print("\ncuobjdump --dump-resource-usage:")
        subprocess.run(["cuobjdump", "--dump-resource-usage", sys.argv[2]], check=False)
    elif len(sys.argv) > 2:
        mismatches = check_binary(sys.argv[2], kernels, names)
    function_names = demangle(sorted({f for f, _ in functions}))
    for (function, arch), (stack, st, ld) in sorted(functions.items()):
        if st or ld:
            spilled.append(f"{short(function_names[function])} ({arch}, called function)")
    if spilled:
        print(f"\n{len(spilled)} kernels or called functions spill registers: {', '.join(spilled)}")
        return 1
    print("\nno kernel spills registers")
    if mismatches:
        print(f"{mismatches} mismatches between the library's cubins and the ptxas log")
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
