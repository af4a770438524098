#!/usr/bin/env python3
"""Tests of check_layers.py on small trees: a clean one passes, each kind of upward or sideways
include fails and is named, and so does a cycle of includes between engine/'s sub-folders and an
include docs/architecture.md's table of them does not allow."""
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


# The CLEAN tree's engine/ folders in a table as docs/architecture.md writes it.
ARCHITECTURE = """# Architecture

| folder | what | includes (in `engine/`) |
|---|---|---|
| `backend/` | the interface | - |
| `model/` | the network | `backend/` |
| `cpu/` | the CPU backend | `backend/`, `model/` |
| `train/` | the trainer | anything above |

After the table.
"""


class DocumentedOrder(unittest.TestCase):
    def test_a_tree_in_the_documented_order_passes(self):
        code, out = run({**CLEAN, "docs/architecture.md": ARCHITECTURE})
        self.assertEqual(code, 0, out)
        self.assertIn("in docs/architecture.md's order", out)

    def test_an_include_the_table_does_not_list_fails_with_its_includes(self):
        doc = ARCHITECTURE.replace("| `backend/`, `model/` |", "| `backend/` |")
        code, out = run({**CLEAN, "docs/architecture.md": doc})
        self.assertEqual(code, 1, out)
        self.assertIn("engine/cpu/ includes engine/model/, which docs/architecture.md's table does not allow it "
                      "(it lists: backend/)", out)
        self.assertIn('engine/cpu/cpu_backend.cpp:2: "engine/model/graph.hpp"', out)

    def test_anything_above_means_the_rows_above(self):
        code, out = run({**CLEAN, "docs/architecture.md": ARCHITECTURE,
                         "engine/model/uses_train.cpp": '#include "engine/backend/backend.hpp"\n',
                         "engine/cpu/x.cpp": '#include "engine/backend/backend.hpp"\n'})
        self.assertEqual(code, 0, out)
        moved = ARCHITECTURE.replace("| `train/` | the trainer | anything above |\n", "").replace(
            "| `backend/` | the interface | - |\n",
            "| `backend/` | the interface | - |\n| `train/` | the trainer | anything above |\n")
        code, out = run({**CLEAN, "docs/architecture.md": moved})
        self.assertEqual(code, 1, out)
        self.assertIn("engine/train/ includes engine/cpu/", out)

    def test_a_folder_missing_from_the_table_or_listed_below_its_row_fails(self):
        code, out = run({**CLEAN, "docs/architecture.md": ARCHITECTURE, "engine/sim/city.cpp": "int x;\n"})
        self.assertEqual(code, 1, out)
        self.assertIn("engine/sim/ is not in docs/architecture.md's table", out)
        upside_down = ARCHITECTURE.replace("| `backend/` | the interface | - |", "| `backend/` | the interface | `cpu/` |")
        code, out = run({**CLEAN, "docs/architecture.md": upside_down})
        self.assertEqual(code, 1, out)
        self.assertIn("engine/backend/ lists cpu/, which is not a row above its own", out)

    def test_a_doc_without_the_table_fails(self):
        code, out = run({**CLEAN, "docs/architecture.md": "# Architecture\n\nNo table.\n"})
        self.assertEqual(code, 1, out)
        self.assertIn("docs/architecture.md: no table of engine's sub-folders", out)


if __name__ == "__main__":
    unittest.main()
