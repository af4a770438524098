#!/usr/bin/env python3
"""Tests of check_layers.py on small trees: a clean one passes, each kind of upward or sideways
include fails and is named, and so does a cycle of includes between engine/'s sub-folders."""
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
    "engine/backend/backend.cpp": '#include "host/conv2d.hpp"\n#include "engine/x.hpp"\n',
    "engine/model/graph.cpp": '#include "engine/model/graph.hpp"\n#include "engine/backend/backend.hpp"\n',
    "engine/cpu/cpu_backend.cpp": '#include "engine/backend/backend.hpp"\n#include "engine/model/graph.hpp"\n',
    "engine/train/trainer.cpp": '#include "engine/cpu/cpu_backend.hpp"\n#include "engine/model/graph.hpp"\n',
    "include/pillarseg/pillarseg.hpp": '#include "pillarseg/pillarseg.h"\n',
}


class CheckLayers(unittest.TestCase):
    def test_clean_tree_passes(self):
        code, out = run(CLEAN)
        self.assertEqual(code, 0, out)

    def test_each_upward_include_fails(self):
        cases = {
            "core/tensor.hpp": '#include "engine/util/image.hpp"\n',
            "host/pfn.cpp": '#include "engine/backend/backend.hpp"\n',
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

    def test_engine_folders_without_a_cycle_pass(self):
        code, out = run(CLEAN)
        self.assertIn("without a cycle", out)

    def test_a_cycle_between_two_engine_folders_fails_with_its_includes(self):
        code, out = run({**CLEAN, "engine/backend/backend.hpp": '#include "core/grid.hpp"\n\n#include "engine/cpu/pfn.hpp"\n'})
        self.assertEqual(code, 1, out)
        self.assertIn("backend/ -> cpu/ -> backend/", out)
        self.assertIn('engine/backend/backend.hpp:3: "engine/cpu/pfn.hpp"', out)
        self.assertIn('engine/cpu/cpu_backend.cpp:1: "engine/backend/backend.hpp"', out)
        # cpu/ includes model/, which includes backend/: a second cycle through that step.
        self.assertIn("model/ -> backend/ -> cpu/ -> model/", out)
        self.assertIn("2 cycle(s)", out)

    def test_a_longer_cycle_names_every_step(self):
        code, out = run({**CLEAN, "engine/backend/options.cpp": '#include "engine/train/trainer.hpp"\n'})
        self.assertEqual(code, 1, out)
        self.assertIn("backend/ -> train/ -> cpu/ -> backend/", out)
        self.assertIn('engine/backend/options.cpp:1: "engine/train/trainer.hpp"', out)
        self.assertIn('engine/train/trainer.cpp:1: "engine/cpu/cpu_backend.hpp"', out)
        self.assertIn('engine/cpu/cpu_backend.cpp:1: "engine/backend/backend.hpp"', out)

    def test_includes_inside_one_engine_folder_are_no_cycle(self):
        code, out = run({**CLEAN, "engine/model/graph.hpp": '#include "engine/model/graph.cpp"\n'})
        self.assertEqual(code, 0, out)


if __name__ == "__main__":
    unittest.main()
