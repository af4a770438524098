#!/usr/bin/env python3
"""Checks that the layers point down (DESIGN.md section 4, STYLE.md rule 13).

core/ includes only core/; host/, kernels/ and weights_io/ include only core/ and their own
folder; the public headers in include/pillarseg/ include only each other and system headers.
engine/, tests/, bench/ and examples/ may include anything below them. Prints every include that
breaks a rule (file:line: what) and exits 1 if there is one.

Usage: check_layers.py [SOURCE_DIR]   (default: the directory above this script)
"""
import pathlib
import re
import sys

ALLOWED = {
    "core": {"core"},
    "host": {"core", "host"},
    "kernels": {"core", "kernels"},
    "weights_io": {"core", "weights_io"},
    "include": {"pillarseg"},
}
SUFFIXES = {".hpp", ".cpp", ".h", ".cu", ".cuh"}
QUOTED = re.compile(r'^\s*#\s*include\s+"([^"]+)"')


def violations(root):
    for layer, allowed in ALLOWED.items():
        folder = root / layer
        if not folder.is_dir():
            continue
        for path in sorted(folder.rglob("*")):
            if path.suffix not in SUFFIXES or not path.is_file():
                continue
            for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
                match = QUOTED.match(line)
                if not match:
                    continue
                target = match.group(1)
                top = target.split("/", 1)[0] if "/" in target else None
                if top not in allowed:
                    rel = path.relative_to(root)
                    yield f"{rel}:{number}: {layer}/ includes \"{target}\" (allowed: " + \
                          ", ".join(sorted(a + "/" for a in allowed)) + ")"


def main():
    root = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else pathlib.Path(__file__).parent.parent)
    found = list(violations(root.resolve()))
    for v in found:
        print(v)
    if found:
        print(f"check_layers: {len(found)} include(s) point up or sideways")
        return 1
    print("check_layers: every layer includes only the layers below it")
    return 0


if __name__ == "__main__":
    sys.exit(main())
