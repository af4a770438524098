#!/usr/bin/env python3
"""Tests of check_layers.py on small trees: a clean one passes, each kind of upward or sideways
include fails and is named."""
import pathlib
import subprocess
import sys
import tempfile
import unittest

SCRIPT = pathlib.Path(__file__).with_name("check_layers.py")


def run(files):
    with tempfile.TemporaryDirectory() as d:
        root = pathlib.Path(d)
        for name, text in files.items():
            path = root / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        done = subprocess.run([sys.executable, str(SCRIPT), str(root)], capture_output=True, text=True)
        return done.returncode, done.stdout


CLEAN = {
    "core/grid.hpp": '#include <cmath>\n#include "core/error.hpp"\n',
    "host/conv2d.cpp": '#include "host/conv2d.hpp"\n#include "core/tensor.hpp"\n',
    "kernels/conv2d.cu": '#include "kernels/common.cuh"\n#include "core/grid.hpp"\n',
    "kernels/emu/emu_runtime.cpp": '#include "kernels/emu/emu_runtime.hpp"\n',
    "weights_io/safetensors.cpp": '#include "weights_io/json.hpp"\n',
    "engine/model/backend.cpp": '#include "host/conv2d.hpp"\n#include "engine/x.hpp"\n',
    "include/pillarseg/pillarseg.hpp": '#include "pillarseg/pillarseg.h"\n',
}


class CheckLayers(unittest.TestCase):
    def test_clean_tree_passes(self):
        code, out = run(CLEAN)
        self.assertEqual(code, 0, out)

    def test_each_upward_include_fails(self):
        cases = {
            "core/tensor.hpp": '#include "engine/util/image.hpp"\n',
            "host/pfn.cpp": '#include "engine/model/backend.hpp"\n',
            "host/relu.cpp": '#include "kernels/relu.cuh"\n',
            "kernels/pfn.cu": '#include "host/pfn.hpp"\n',
            "kernels/emu/emu_device.hpp": '  #  include "engine/core/error.hpp"\n',
            "weights_io/json.cpp": '#include "host/softmax.hpp"\n',
            "include/pillarseg/pillarseg.hpp": '#include "engine/api/segmenter.hpp"\n',
        }
        for name, text in cases.items():
            with self.subTest(name=name):
                code, out = run({**CLEAN, name: text})
                self.assertEqual(code, 1, out)
                self.assertIn(name + ":1:", out)


if __name__ == "__main__":
    unittest.main()
