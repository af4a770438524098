#!/usr/bin/env python3
"""Compares what the emulated tests read back under other schedules with forward's.

usage: compare_emu_digests.py DIGESTS_DIR MIN_TESTS

DIGESTS_DIR holds forward/, reverse/ and random/ (tests/support/emu_digests.cpp writes one file
per test: the hashes of its device-to-host copies, in order). Every test of reverse/ and random/
must have read back exactly what it read under forward/; a difference is a race (the result
depends on the order of threads or blocks) or a read of uninitialised shared memory. Fails also
when fewer than MIN_TESTS tests were compared under each schedule, so that a run that recorded
nothing cannot pass.
"""
import pathlib
import sys


def main() -> int:
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    root = pathlib.Path(sys.argv[1])
    minimum = int(sys.argv[2])
    forward = root / "forward"
    failures = []
    for schedule in ("reverse", "random"):
        compared = 0
        for path in sorted((root / schedule).glob("*")):
            reference = forward / path.name
            if not reference.exists():
                failures.append(f"{schedule}: {path.name} has no forward run to compare with")
                continue
            ours, theirs = path.read_text().split(), reference.read_text().split()
            compared += 1
            if ours == theirs:
                continue
            if len(ours) != len(theirs):
                failures.append(f"{schedule}: {path.name} read back {len(ours)} buffers, forward "
                                f"{len(theirs)}")
                continue
            first = next(i for i, (a, b) in enumerate(zip(ours, theirs)) if a != b)
            differing = sum(a != b for a, b in zip(ours, theirs))
            failures.append(f"{schedule}: {path.name}: copy {first} (of {len(ours)}; {differing} "
                            f"differ) is not forward's bits: a race or a read of uninitialised "
                            f"shared memory")
        print(f"{schedule}: {compared} tests compared with forward")
        if compared < minimum:
            failures.append(f"{schedule}: only {compared} tests compared (at least {minimum} "
                            f"expected): were the {schedule} runs recorded into {root / schedule}?")
    for failure in failures:
        print(failure)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
